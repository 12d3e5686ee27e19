"""The official-MOC switches: the per-term update schedule, the next-step importance correction, the diagnostics."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.modules import OptionCriticActor, OptionHeads, make_option_critic
from torchrl_offhrl.objectives import OptionCriticLoss


def _constant_heads(logits, term_prob, obs_dim=2):
    """Heads whose outputs do not depend on the state: zero weights, chosen biases."""
    heads = OptionHeads(obs_dim, 1, len(logits), hidden=(4,))
    with torch.no_grad():
        for p in heads.parameters():
            p.zero_()
        heads.option_head[-1].bias.copy_(torch.tensor(logits).log())
        heads.termination_head[-1].bias.copy_(torch.logit(torch.tensor(term_prob)))
    return heads


def test_next_step_correction_hand_computed():
    """pi_O = (0.25, 0.75), beta = (0.2, 0.6) everywhere; options 0, 1, 1 over three steps of one env.

    P(o'=1 | s', o=0) = 0.2 * 0.75 = 0.15 and P(o'=1 | s', o=1) = 0.6 * 0.75 + 0.4 = 0.85, so the
    ratio log P(o_{t+1}|s_{t+1}, o) - log P(o_{t+1}|s_{t+1}, o_t) is (0, log(0.85/0.15)) at t=0 (o_t=0),
    (log(0.15/0.85), 0) at t=1 (o_t=1), and 0 at the batch's last step (its next option is not in the batch).
    """
    actor = OptionCriticActor(_constant_heads([0.25, 0.75], [0.2, 0.6]), low=-1.0, high=1.0)
    critic = make_option_critic(2, 2, hidden=(4,))
    loss = OptionCriticLoss(actor, critic, importance_correction="next_step")
    td = TensorDict(
        {
            "observation": torch.zeros(1, 3, 2),
            "option": torch.tensor([[0, 1, 1]]),
            "next": {"observation": torch.zeros(1, 3, 2), "done": torch.zeros(1, 3, 1, dtype=torch.bool)},
        },
        batch_size=[1, 3],
    )
    loss.annotate_next_assignment(td)
    r = math.log(0.85 / 0.15)
    expected = torch.tensor([[[0.0, r], [-r, 0.0], [0.0, 0.0]]])
    torch.testing.assert_close(td["next_assignment_log_ratio"], expected)
    # a done cuts it: the next row belongs to another episode
    td["next", "done"][0, 0] = True
    loss.annotate_next_assignment(td)
    torch.testing.assert_close(td["next_assignment_log_ratio"][0, 0], torch.zeros(2))
    # and the loss uses it: importance_log_ratio adds exactly the stored ratio to the action ratio
    flat = td.reshape(-1)
    flat["option_log_probs"] = torch.zeros(3, 2)
    new_logp = torch.zeros(3, 2)
    torch.testing.assert_close(loss.importance_log_ratio(flat, new_logp), flat["next_assignment_log_ratio"])


def test_next_step_correction_needs_the_batch_prepared():
    actor = OptionCriticActor(_constant_heads([0.5, 0.5], [0.5, 0.5]), low=-1.0, high=1.0)
    loss = OptionCriticLoss(actor, make_option_critic(2, 2, hidden=(4,)), importance_correction="next_step")
    flat = TensorDict({"option": torch.tensor([0]), "option_log_probs": torch.zeros(1, 2)}, batch_size=[1])
    with pytest.raises(KeyError, match="prepare_batch"):
        loss.importance_log_ratio(flat, torch.zeros(1, 2))
    with pytest.raises(ValueError, match="importance_correction must be one of"):
        OptionCriticLoss(actor, make_option_critic(2, 2, hidden=(4,)), importance_correction="double")


def _moc_env():
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    return make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                          ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=8)


@pytest.mark.parametrize("schedule", ["joint", "per_term"])
def test_update_schedule_counts_optimizer_steps(schedule):
    """per_term: the termination head and pi_O get exactly one Adam step per batch, the rest one per minibatch."""
    from torchrl_offhrl.agents import make_agent

    env = _moc_env()
    agent = make_agent("moc", env, num_options=2, hidden_sizes=[8], epochs=3, minibatch_size=16, update_schedule=schedule,
                       importance_correction="next_step" if schedule == "per_term" else "assignment", termination_lr=1e-3, option_lr=2e-3)
    agent.attach(env)
    before = {n: p.detach().clone() for n, p in agent.loss.named_parameters()}
    for _ in range(2):
        with torch.no_grad():
            batch = env.rollout(8, agent.policy, break_when_any_done=False)  # [8 envs, 8 steps] = 64 frames
        out = agent.update(batch)
    minibatches = 3 * 64 // 16
    assert out["updates"] == minibatches
    steps = lambda opt: {int(s["step"]) for s in opt.state.values()}  # noqa: E731
    if schedule == "joint":
        assert agent.termination_optimizer is None
        assert steps(agent.optimizer) == {2 * minibatches}
        return
    assert steps(agent.optimizer) == {2 * minibatches}
    assert steps(agent.termination_optimizer) == {2} and steps(agent.option_optimizer) == {2}
    assert agent.termination_optimizer.param_groups[0]["lr"] == 1e-3 and agent.option_optimizer.param_groups[0]["lr"] == 2e-3
    names = {n for n, p in agent.loss.named_parameters() if not torch.equal(p, before[n])}
    assert any(".termination_head." in n for n in names) and any(".option_head." in n for n in names)
    # the three groups partition the parameters
    groups = [agent.optimizer, agent.termination_optimizer, agent.option_optimizer]
    ids = [id(p) for opt in groups for g in opt.param_groups for p in g["params"]]
    assert len(ids) == len(set(ids)) == len(list(agent.loss.parameters()))
    # and a checkpoint holds all three
    again = make_agent("moc", env, num_options=2, hidden_sizes=[8], update_schedule="per_term", importance_correction="next_step")
    again.load_state_dict(agent.state_dict())
    assert steps(again.termination_optimizer) == {2}


def _constant_q_loss_and_batch(value_target):
    """A loss with Q = (1, 3) and pi_O = (0.25, 0.75) everywhere, and a 4-step batch: options 0, 0, 1, 1 after 0, 0, 1, 0."""
    actor = OptionCriticActor(_constant_heads([0.25, 0.75], [0.5, 0.5]), low=-1.0, high=1.0)
    critic = make_option_critic(2, 2, hidden=(4,))
    with torch.no_grad():
        for p in critic.parameters():
            p.zero_()
        critic.module.net[-1].bias.copy_(torch.tensor([1.0, 3.0]))
    td = TensorDict(
        {
            "observation": torch.zeros(4, 2), "action": torch.zeros(4, 1), "option": torch.tensor([0, 0, 1, 1]),
            "prev_option": torch.tensor([0, 0, 1, 0]), "is_init": torch.tensor([True, False, False, False]).unsqueeze(-1),
            "option_log_probs": torch.zeros(4, 2), "option_assignment_log_prob": torch.full((4, 2), 0.5).log(),
            "advantage": torch.zeros(4, 1), "value_target": torch.as_tensor(value_target, dtype=torch.float32).reshape(4, 1),
        },
        batch_size=[4],
    )
    return OptionCriticLoss(actor, critic), td


def test_diagnostics_hand_computed():
    """Q = (1, 3), pi_O = (0.25, 0.75): V = 2.5, so Q(s, o_prev) - V is -1.5 for option 0 and +0.5 for option 1."""
    loss, td = _constant_q_loss_and_batch([0.0, 0.0, 0.0, 0.0])
    out = loss(td)
    # non-start steps: prev 0 (1 - 2.5 = -1.5), 1 (+0.5), 0 (-1.5)
    torch.testing.assert_close(out["termination_advantage"], torch.tensor(-2.5 / 3))
    torch.testing.assert_close(out["termination_advantage_positive"], torch.tensor(1 / 3))
    # usage 0.5 / 0.5: entropy log 2
    torch.testing.assert_close(out["option_usage_entropy"], torch.tensor(math.log(2)))


def test_explained_variance_hand_computed():
    """explained_variance = 1 - Var(G - Q(s, o_t)) / Var(G), on the executed option's Q (constant Q = (1, 3))."""
    loss, td = _constant_q_loss_and_batch([2.0, 0.0, 4.0, 3.0])
    out = loss(td)
    # executed Q: 1, 1, 3, 3; G - Q: 1, -1, 1, 0 -> var 0.6875; Var(G) = 2.1875
    assert out["explained_variance"].item() == pytest.approx(1 - 0.6875 / 2.1875)


def test_action_std_is_the_executed_options_scale():
    """std 2 for option 0 and 3 for option 1; options 0, 0, 1, 1 ran: action_std = (2 + 2 + 3 + 3) / 4."""
    loss, td = _constant_q_loss_and_batch([0.0, 0.0, 0.0, 0.0])
    with torch.no_grad():
        loss.actor_network.heads.log_std.copy_(torch.tensor([[math.log(2.0)], [math.log(3.0)]]))
    out = loss(td)
    assert out["action_std"].item() == pytest.approx(2.5)


@pytest.mark.parametrize("gain", [0.01, 1.0])
def test_intra_head_gain_sets_the_initial_means_scale(gain):
    """The intra-option means' last layer is orthogonal with the given gain: W W^T = gain^2 I (orthogonal rows of norm gain)."""
    torch.manual_seed(0)
    heads = OptionHeads(5, 3, num_options=2, hidden=(16,), intra_head_gain=gain)
    w = heads.intra_head[-1].weight  # [n * A, hidden]: orthogonal rows of norm `gain`
    torch.testing.assert_close(w @ w.T, gain**2 * torch.eye(6), atol=1e-5 * max(gain**2, 1e-2), rtol=0)



class PushUpLoss(OptionCriticLoss):
    """A contributor's option-critic variant, defined here: a termination loss whose gradient pushes every beta up."""

    calls: list = []

    def termination_loss(self, td):
        PushUpLoss.calls.append(td.batch_size.numel())
        return {"loss_termination": -td.get(self.tensor_keys.termination_probs).mean()}, {}


class CostlyLoss(OptionCriticLoss):
    """A loss with an argument of its own (a deliberation cost kept on the loss)."""

    def __init__(self, *args, deliberation_cost: float = 0.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.deliberation_cost = deliberation_cost


def test_moc_agent_takes_its_loss_arguments_from_the_loss():
    """MOCAgent declares no argument of OptionCriticLoss: every loss argument (eta, gamma, the coefficients, ...) is
    accepted from the config with the loss's own default (or the agent's deviation, xi and importance_correction) and
    reaches the loss unchanged; a loss named by algo.loss brings its own arguments; a typo is still refused."""
    import inspect

    from torchrl_offhrl.agents import agent_defaults, make_agent
    from torchrl_offhrl.agents.moc import MOCAgent

    own = inspect.signature(MOCAgent.__init__).parameters
    loss_args = {k for k, p in inspect.signature(OptionCriticLoss.__init__).parameters.items() if p.kind is p.KEYWORD_ONLY}
    assert not (loss_args & set(own)) - {"num_options"}  # declared once: in the loss
    defaults = agent_defaults("moc")
    assert loss_args - {"num_options"} <= set(defaults)
    assert (defaults["eta"], defaults["termination_coef"], defaults["xi"], defaults["importance_correction"]) == (0.7, 1.0, 0.01, "next_step")
    env = _moc_env()
    agent = make_agent("moc", env, {"eta": 0.3, "termination_coef": 0.5, "gamma": 0.9}, hidden_sizes=[8])
    assert (agent.loss.eta, agent.loss.termination_coef, agent.loss.xi, agent.loss.importance_correction) == (0.3, 0.5, 0.01, "next_step")
    assert agent.loss._gamma == 0.9  # what its value estimator is built with
    custom = make_agent("moc", env, {"loss": f"{__name__}.CostlyLoss", "deliberation_cost": 0.25}, hidden_sizes=[8])
    assert type(custom.loss) is CostlyLoss and custom.loss.deliberation_cost == 0.25
    with pytest.raises(TypeError, match=r"unknown hyper-parameter\(s\) \['deliberation_cost'\]"):
        make_agent("moc", env, {"deliberation_cost": 0.25}, hidden_sizes=[8])  # OptionCriticLoss has no such argument
    # a registered subclass of the agent: its own loss class and defaults are the ones read, not MOCAgent's
    from torchrl_offhrl.agents import AGENTS
    from torchrl_offhrl.agents.registry import register_agent, unknown_hyperparameters

    try:
        register_agent("moc_costly")(type("CostlyAgent", (MOCAgent,), {"loss_class": CostlyLoss, "loss_defaults": {"xi": 0.0}}))
        assert agent_defaults("moc_costly")["deliberation_cost"] == 0.0 and agent_defaults("moc_costly")["xi"] == 0.0
        assert unknown_hyperparameters("moc_costly", {"deliberation_cost": 0.5}) == []
        sub = make_agent("moc_costly", env, {"deliberation_cost": 0.5}, hidden_sizes=[8])
        assert type(sub.loss) is CostlyLoss and sub.loss.deliberation_cost == 0.5 and sub.loss.xi == 0.0
    finally:
        AGENTS.pop("moc_costly", None)
    # the run's config check names a loss it cannot import among its problems, before any work
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.schema import validate_config

    with pytest.raises(ValueError, match=r"algo.loss='no_such_pkg.Loss': cannot import"):
        validate_config(compose("offline_train", ["algo=moc", "algo.loss=no_such_pkg.Loss"]))


def test_subclassed_loss_trains_through_moc_agent():
    """A contributor's OptionCriticLoss subclass trains through MOCAgent with no library code touched (CONTRIBUTING.md):
    named in the config (algo.loss, a dotted path) or set by a registered subclass of the agent; its overridden term is
    the one the termination head learns from."""
    from torchrl_offhrl.agents import AGENTS, make_agent
    from torchrl_offhrl.agents.moc import MOCAgent
    from torchrl_offhrl.agents.registry import register_agent

    env = _moc_env()
    try:
        register_agent("moc_push_up")(type("PushUpAgent", (MOCAgent,), {"loss_class": PushUpLoss}))
        agents = [make_agent("moc", env, {"loss": f"{__name__}.PushUpLoss"}, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=32,
                             termination_lr=1e-2),
                  make_agent("moc_push_up", env, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=32, termination_lr=1e-2)]
    finally:
        AGENTS.pop("moc_push_up", None)
    for agent in agents:
        assert type(agent.loss) is PushUpLoss
        agent.attach(env)
        probe = env.reset()["observation"]
        beta0 = agent.policy.heads(probe)[3].mean()
        PushUpLoss.calls.clear()
        for _ in range(3):
            with torch.no_grad():
                batch = env.rollout(8, agent.policy, break_when_any_done=False)
            agent.update(batch)
        assert PushUpLoss.calls.count(64) == 3  # the per-term schedule steps it on the whole 64-frame batch, once per update
        assert agent.policy.heads(probe)[3].mean() > beta0 + 0.01
    env = _moc_env()
    with pytest.raises(ValueError, match=r"algo.loss='no_such_pkg.Loss': cannot import 'no_such_pkg'"):
        make_agent("moc", env, {"loss": "no_such_pkg.Loss"})
    with pytest.raises(TypeError, match=r"algo.loss='collections.OrderedDict' is not a subclass of OptionCriticLoss"):
        make_agent("moc", env, {"loss": "collections.OrderedDict"})


def test_a_subclassed_loss_named_in_the_config_trains_end_to_end(hopper_file, cache, tmp_path):
    """offhrl's loop with algo.loss=<this module>.PushUpLoss: the run trains, checkpoints and records the loss it used."""
    import json

    from test_recipes import _cfg

    from torchrl_offhrl.recipes.train import train

    PushUpLoss.calls.clear()
    summary = train(_cfg("moc", hopper_file, tmp_path, extra=[f"algo.loss={__name__}.PushUpLoss"]), progress=False)
    # per 64-frame batch: 2 epochs of one 64-frame minibatch (every term computed) + the per-term full-batch step
    assert summary["frames"] == 256 and PushUpLoss.calls == [64] * (256 // 64) * (2 + 1)
    cfg = json.loads((Path(summary["run_dir"]) / "config.json").read_text())
    assert cfg["algo"]["loss"] == f"{__name__}.PushUpLoss"


def test_policy_ema_averages_the_weights_and_is_what_evaluations_use():
    """algo.policy_ema: after each update the averaged copy moves policy_ema of the way to the policy's new weights
    (hand-computed on every parameter); eval_policy is that copy; it is checkpointed; off (None), eval_policy is the policy."""
    from torchrl_offhrl.agents import make_agent

    env = _moc_env()
    agent = make_agent("moc", env, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=32, policy_ema=0.25)
    agent.attach(env)
    assert agent.eval_policy is agent.averaged_policy and agent.eval_policy is not agent.policy
    for _ in range(2):
        before = [p.detach().clone() for p in agent.averaged_policy.parameters()]
        with torch.no_grad():
            batch = env.rollout(8, agent.policy, break_when_any_done=False)
        agent.update(batch)
        for avg, old, new in zip(agent.averaged_policy.parameters(), before, agent.policy.parameters()):
            torch.testing.assert_close(avg, old + 0.25 * (new.detach() - old))
    assert any(not torch.equal(a, p) for a, p in zip(agent.averaged_policy.parameters(), agent.policy.parameters()))
    again = make_agent("moc", env, num_options=2, hidden_sizes=[8], policy_ema=0.25)
    again.load_state_dict(agent.state_dict())
    for a, b in zip(again.averaged_policy.parameters(), agent.averaged_policy.parameters()):
        torch.testing.assert_close(a, b)
    plain = make_agent("moc", env, num_options=2, hidden_sizes=[8])
    assert plain.eval_policy is plain.policy and "averaged_policy" not in plain.state_dict()
    with pytest.raises(ValueError, match=r"algo.policy_ema must be in \(0, 1\]"):
        make_agent("moc", env, num_options=2, hidden_sizes=[8], policy_ema=1.5)


def test_log_std_lr_gives_the_log_stds_their_own_annealed_step_size():
    """algo.log_std_lr: the intra-option log-stds sit in their own Adam group at that step size, so one Adam step moves
    each by at most about log_std_lr (Adam's first step is lr * sign(grad)), while the other weights move by <= lr;
    null keeps one group (the runs made before the switch); annealing scales both groups alike."""
    from torchrl_offhrl.agents import make_agent

    env = _moc_env()
    agent = make_agent("moc", env, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=512, lr=1e-4, log_std_lr=0.05, anneal_lr=True)
    agent.attach(env)
    groups = agent.optimizer.param_groups
    assert [g["lr"] for g in groups] == [1e-4, 0.05]
    log_std = next(p for n, p in agent.loss.named_parameters() if n.endswith(".log_std"))
    assert groups[1]["params"] == [log_std] and all(p is not log_std for p in groups[0]["params"])
    before = log_std.detach().clone()
    others = [p.detach().clone() for p in groups[0]["params"]]
    with torch.no_grad():
        batch = env.rollout(64, agent.policy, break_when_any_done=False)
    agent.update(batch)
    moved = (log_std.detach() - before).abs()
    assert moved.max() <= 0.05 * 1.001 and moved.max() > 1e-3  # one minibatch step: |delta| ~ 0.05 where the gradient is steady
    assert max((p.detach() - o).abs().max().item() for p, o in zip(groups[0]["params"], others)) <= 1e-4 * 1.001
    agent.set_progress(0.5)
    assert [g["lr"] for g in agent.optimizer.param_groups] == pytest.approx([5e-5, 0.025])
    plain = make_agent("moc", env, num_options=2, hidden_sizes=[8])
    assert len(plain.optimizer.param_groups) == 1
    with pytest.raises(ValueError, match="algo.log_std_lr must be a positive"):
        make_agent("moc", env, num_options=2, hidden_sizes=[8], log_std_lr=0.0)


def test_final_log_std_schedules_the_log_stds_on_a_line_instead_of_learning_them():
    """algo.final_log_std: the log-stds are in no optimiser, an update leaves them where they are, and set_progress puts
    every option's log-std at init + (final - init) * fraction (hand-computed: -1 at 0.25 of the way from 0 to -4)."""
    from torchrl_offhrl.agents import make_agent

    env = _moc_env()
    agent = make_agent("moc", env, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=512, init_log_std=0.0, final_log_std=-4.0,
                       policy_ema=0.5)
    agent.attach(env)
    log_std = agent.policy.heads.log_std
    assert not log_std.requires_grad
    assert all(p is not log_std for opt in agent.optimizers() for g in opt.param_groups for p in g["params"])
    agent.set_progress(0.25)
    assert torch.equal(log_std, torch.full_like(log_std, -1.0))
    assert torch.equal(agent.averaged_policy.heads.log_std, torch.full_like(log_std, -1.0))
    with torch.no_grad():
        batch = env.rollout(64, agent.policy, break_when_any_done=False)
    scale = agent.policy.get_option_heads(batch.clone())["option_scale"]
    assert torch.allclose(scale, torch.full_like(scale, float(torch.tensor(-1.0).exp())))
    agent.update(batch)
    assert torch.equal(log_std, torch.full_like(log_std, -1.0))
    agent.set_progress(1.0)
    assert torch.equal(log_std, torch.full_like(log_std, -4.0))
    with pytest.raises(ValueError, match="leave algo.log_std_lr null"):
        make_agent("moc", env, num_options=2, hidden_sizes=[8], final_log_std=-1.0, log_std_lr=1e-3)


def test_prior_coef_is_half_the_squared_norm_of_the_executed_options_mode_action_and_pulls_it_in():
    """algo.prior_coef: with eta=0 the weights are the executed option's one-hot, so loss_prior is
    coef * 0.5 * mean_b ||a_{o_b}(s_b)||^2 with a = 2 tanh(loc) on the [-2, 2] latent box (hand-computed from the
    heads); a coefficient of 0 leaves the loss's output as it was (no loss_prior key); training on the term alone
    shrinks the mode actions."""
    from torchrl_offhrl.agents import make_agent

    env = _moc_env()
    agent = make_agent("moc", env, num_options=2, hidden_sizes=[8], epochs=1, minibatch_size=512, eta=0.0, prior_coef=0.5, intra_head_gain=1.0,
                       anneal_lr=False, lr=1e-2)
    agent.attach(env)
    with torch.no_grad():
        batch = env.rollout(32, agent.policy, break_when_any_done=False)
    agent.prepare(batch)
    flat = batch.reshape(-1)
    out = agent.loss(flat)
    with torch.no_grad():
        _, loc, _, _ = agent.policy.heads(flat["observation"])
        low, high = agent.policy.low, agent.policy.high
        mode = low + (high - low) * (torch.tanh(loc) + 1) / 2  # [B, n, A]
        executed = mode.gather(1, flat["option"].long().reshape(-1, 1, 1).expand(-1, 1, mode.shape[-1])).squeeze(1)
        expected = 0.5 * 0.5 * executed.pow(2).sum(-1).mean()
    assert torch.allclose(out["loss_prior"], expected, rtol=1e-5)
    assert "loss_prior" not in make_agent("moc", env, num_options=2, hidden_sizes=[8]).loss(flat.clone()).keys()
    before = float(expected)
    opt = torch.optim.SGD(agent.policy.parameters(), lr=0.5)
    for _ in range(20):
        opt.zero_grad()
        agent.loss(flat)["loss_prior"].backward()
        opt.step()
    assert float(agent.loss(flat)["loss_prior"]) < 0.5 * before
    with pytest.raises(ValueError, match="prior_coef must be >= 0"):
        make_agent("moc", env, num_options=2, hidden_sizes=[8], prior_coef=-1.0)
