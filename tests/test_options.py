"""Option-critic modules and OptionCriticLoss: hand-computed cases and rollout invariants."""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from torchrl_offhrl.modules import OptionCriticActor, OptionHeads, make_option_critic
from torchrl_offhrl.objectives import OptionCriticLoss


def _constant_heads(logits, loc, log_std, term_logit, obs_dim=2):
    """Heads whose outputs do not depend on the state: zero weights, chosen biases."""
    n, a = len(logits), len(loc[0])
    heads = OptionHeads(obs_dim, a, n, hidden=(4,))
    with torch.no_grad():
        for p in heads.parameters():
            p.zero_()
        heads.option_head[-1].bias.copy_(torch.tensor(logits))
        heads.intra_head[-1].bias.copy_(torch.tensor(loc).reshape(-1))
        heads.termination_head[-1].bias.copy_(torch.tensor(term_logit))
        heads.log_std.copy_(torch.tensor(log_std))
    return heads


def _constant_critic(q, obs_dim=2):
    critic = make_option_critic(obs_dim, len(q), hidden=(4,))
    with torch.no_grad():
        for p in critic.parameters():
            p.zero_()
        critic.module.net[-1].bias.copy_(torch.tensor(q))
    return critic


def _tanh_normal_logp(a, loc, std):
    """log-density of a = tanh(u), u ~ N(loc, std), box [-1, 1]: written independently of torchrl."""
    u = torch.atanh(torch.as_tensor(a))
    return torch.distributions.Normal(loc, std).log_prob(u) - torch.log1p(-torch.tanh(u) ** 2)


def _batch(actions, option, prev, is_init, old_logp, assign, adv, target, obs_dim=2):
    b = len(actions)
    return TensorDict(
        {
            "observation": torch.zeros(b, obs_dim),
            "action": torch.tensor(actions).reshape(b, 1),
            "option": torch.tensor(option),
            "prev_option": torch.tensor(prev),
            "is_init": torch.tensor(is_init).reshape(b, 1),
            "option_start": torch.tensor(is_init),
            "termination_prob": torch.full((b,), 0.5),
            "option_log_probs": torch.tensor(old_logp),
            "option_assignment_log_prob": torch.tensor(assign).log(),
            "advantage": torch.tensor(adv).reshape(b, 1),
            "value_target": torch.tensor(target).reshape(b, 1),
        },
        batch_size=[b],
    )


LOCS = [[0.0], [0.5], [-0.4]]
ACTIONS = [0.2, -0.3, 0.6]
OPTION = [0, 1, 0]
ASSIGN = [[0.7, 0.2, 0.1], [0.3, 0.6, 0.1], [0.8, 0.1, 0.1]]
ADV = [1.0, -2.0, 0.5]


def _loss_setup(eta, old_shift=0.1):
    heads = _constant_heads([0.0, 0.0, 0.0], LOCS, [[0.0]] * 3, [0.0, 0.0, 0.0])
    actor = OptionCriticActor(heads, low=-1.0, high=1.0)
    critic = _constant_critic([0.0, 0.0, 0.0])
    new = torch.stack([_tanh_normal_logp(torch.tensor(ACTIONS), torch.tensor(l[0]), torch.tensor(1.0)) for l in LOCS], -1)
    old = new - old_shift  # the data's log-probs: current ratio exp(old_shift) before correction
    batch = _batch(ACTIONS, OPTION, [0, 0, 0], [True, False, False], old.tolist(), ASSIGN, ADV, [0.0] * 3)
    loss = OptionCriticLoss(actor, critic, eta=eta, clip_epsilon=0.2, normalize_advantage=False)
    return loss, batch, new, old


def _expected_objective(new, old, eta, eps=0.2):
    o = torch.tensor(OPTION)
    P = torch.tensor(ASSIGN)
    A = torch.tensor(ADV)
    old_exec = old[torch.arange(3), o]
    ratio = torch.exp(new - old_exec[:, None] + P.log() - P.log()[torch.arange(3), o][:, None])
    surr = torch.minimum(ratio * A[:, None], ratio.clamp(1 - eps, 1 + eps) * A[:, None])
    w = P if eta == 1 else torch.nn.functional.one_hot(o, 3).float()
    return -(w * surr).sum(-1).mean(), ratio


@pytest.mark.parametrize("eta", [0.0, 1.0])
def test_objective_matches_hand_computation(eta):
    loss, batch, new, old = _loss_setup(eta)
    out = loss(batch)
    expected, _ratio = _expected_objective(new, old, eta)
    torch.testing.assert_close(out["loss_objective"], expected, rtol=1e-5, atol=1e-6)
    assert float(out["z"]) == eta


def test_eta_zero_is_ppo_on_executed_option():
    """eta=0: the ratio of the executed option is the plain PPO ratio, other options get no gradient."""
    loss, batch, _new, _old = _loss_setup(0.0, old_shift=0.1)
    out = loss(batch)
    # hand value: ratio exp(0.1) = 1.105 inside the clip, so loss = -mean(1.105 * A)
    assert out["loss_objective"].item() == pytest.approx(-math.exp(0.1) * sum(ADV) / 3, rel=1e-5)
    out["loss_objective"].backward()
    grad = loss.actor_network_params["heads", "intra_head", "2", "bias"].grad  # 3 options x 1 action
    assert grad[0] != 0 and grad[1] != 0  # options 0 and 1 were executed
    assert grad[2] == 0  # option 2 never executed: no update with eta=0


def test_eta_one_updates_every_consistent_option():
    loss, batch, _new, _old = _loss_setup(1.0, old_shift=0.1)
    loss(batch)["loss_objective"].backward()
    grad = loss.actor_network_params["heads", "intra_head", "2", "bias"].grad
    assert (grad != 0).all()


def test_importance_correction_values():
    """With current == old parameters, the ratio of option o on data of o_t is pi_o/pi_ot * P(o)/P(o_t)."""
    loss, batch, new, old = _loss_setup(1.0, old_shift=0.0)
    _, ratio = _expected_objective(new, old, 1.0)
    # element 1 was generated by option 1; the ratio for option 0 is a density ratio times 0.3/0.6
    p0 = _tanh_normal_logp(torch.tensor(-0.3), torch.tensor(0.0), torch.tensor(1.0)).exp()
    p1 = _tanh_normal_logp(torch.tensor(-0.3), torch.tensor(0.5), torch.tensor(1.0)).exp()
    assert ratio[1, 0].item() == pytest.approx((p0 / p1).item() * 0.3 / 0.6, rel=1e-5)
    assert ratio[1, 1].item() == pytest.approx(1.0)
    # the loss uses exactly these ratios: single out element 1 and option 0 (P = 0.3 there)
    one = batch[1:2].clone()
    one["option_assignment_log_prob"] = torch.tensor([[0.3, 0.6, 1e-12]]).log()
    out = loss(one)
    r = (p0 / p1).item() * 0.3 / 0.6
    a = ADV[1]  # negative advantage: the surrogate is min(r A, clip(r) A)
    surr0 = min(r * a, min(max(r, 0.8), 1.2) * a)
    torch.testing.assert_close(out["loss_objective"].double(), torch.tensor(-(0.3 * surr0 + 0.6 * 1.0 * a)).double(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("q_prev,direction", [(-1.0, +1), (2.0, -1)])
def test_termination_gradient_sign(q_prev, direction):
    """Q(s, o_prev) < V(s): terminating more lowers the loss; Q > V: terminating less."""
    heads = _constant_heads([0.0, 0.0], [[0.0], [0.0]], [[0.0]] * 2, [0.0, 0.0])
    actor = OptionCriticActor(heads)
    critic = _constant_critic([q_prev, 0.5])  # V = (q_prev + 0.5) / 2
    loss = OptionCriticLoss(actor, critic, xi=0.0, normalize_advantage=False)
    batch = _batch([0.1, 0.1], [0, 0], [0, 0], [False, True], [[0.0, 0.0]] * 2, [[0.5, 0.5]] * 2, [0.0, 0.0], [0.0, 0.0])
    out = loss(batch)
    v = (q_prev + 0.5) / 2
    # only the non-initial step counts; beta = sigmoid(0) = 0.5
    assert out["loss_termination"].item() == pytest.approx(0.5 * (q_prev - v))
    out["loss_termination"].backward()
    g = loss.actor_network_params["heads", "termination_head", "2", "bias"].grad[0]
    # gradient descent moves the termination logit of option 0 in `direction`
    assert torch.sign(-g).item() == direction


def test_option_policy_moves_towards_better_option():
    heads = _constant_heads([0.0, 0.0], [[0.0], [0.0]], [[0.0]] * 2, [0.0, 0.0])
    actor = OptionCriticActor(heads)
    critic = _constant_critic([1.0, 3.0])
    loss = OptionCriticLoss(actor, critic, option_entropy_coef=0.0)
    batch = _batch([0.1], [0], [0], [True], [[0.0, 0.0]], [[0.5, 0.5]], [0.0], [0.0])
    out = loss(batch)
    # -(1 * sum_o pi(o) (Q(o) - V)) with pi uniform is 0; its gradient favours option 1
    assert out["loss_option"].item() == pytest.approx(0.0, abs=1e-6)
    out["loss_option"].backward()
    g = loss.actor_network_params["heads", "option_head", "2", "bias"].grad
    assert g[1] < 0 < g[0]


def test_option_gae_hand_computed():
    """One trajectory of 3 steps, terminal at the end; U(s', o) from constant heads and critic."""
    heads = _constant_heads([0.0, math.log(3.0)], [[0.0], [0.0]], [[0.0]] * 2, [0.0, math.log(1 / 3)])
    actor = OptionCriticActor(heads)
    critic = _constant_critic([1.0, 2.0])
    loss = OptionCriticLoss(actor, critic)
    loss.make_value_estimator(gamma=0.9, lmbda=0.5)
    td = TensorDict(
        {
            "observation": torch.zeros(3, 2),
            "option": torch.tensor([0, 1, 1]),
            "next": {
                "observation": torch.zeros(3, 2),
                "reward": torch.tensor([[1.0], [0.0], [2.0]]),
                "done": torch.tensor([[False], [False], [True]]),
                "terminated": torch.tensor([[False], [False], [True]]),
            },
        },
        batch_size=[3],
    )
    loss.value_estimator(td)
    # pi_O = (1/4, 3/4), V = 1/4 + 3/2 = 1.75; beta = (1/2, 1/4)
    u0 = 0.5 * 1.0 + 0.5 * 1.75  # option 0
    u1 = 0.75 * 2.0 + 0.25 * 1.75  # option 1
    d = [1.0 + 0.9 * u0 - 1.0, 0.0 + 0.9 * u1 - 2.0, 2.0 - 2.0]
    a2 = d[2]
    a1 = d[1] + 0.9 * 0.5 * a2
    a0 = d[0] + 0.9 * 0.5 * a1
    torch.testing.assert_close(td["advantage"].reshape(-1), torch.tensor([a0, a1, a2]))
    torch.testing.assert_close(td["value_target"].reshape(-1), torch.tensor([a0 + 1.0, a1 + 2.0, a2 + 2.0]))


def test_loss_validates_arguments():
    heads = OptionHeads(2, 1, 3, hidden=(4,))
    actor = OptionCriticActor(heads)
    critic = make_option_critic(2, 3, hidden=(4,))
    with pytest.raises(ValueError, match="num_options"):
        OptionCriticLoss(actor, critic, num_options=4)
    with pytest.raises(ValueError, match="eta"):
        OptionCriticLoss(actor, critic, eta=1.5)
    with pytest.raises(NotImplementedError, match="GAE"):
        from torchrl.objectives.utils import ValueEstimators

        OptionCriticLoss(actor, critic).make_value_estimator(ValueEstimators.TD0)


# ----------------------------------------------------------------- rollouts
class EpisodesOfDifferentLengths(EnvBase):
    """Batched env: env i ends its episodes every ``lengths[i]`` steps (partial resets)."""

    def __init__(self, lengths):
        super().__init__(batch_size=[len(lengths)])
        self.lengths = torch.tensor(lengths)
        n = len(lengths)
        self.observation_spec = Composite(observation=Unbounded((n, 2)), shape=(n,))
        self.action_spec = Bounded(-1.0, 1.0, (n, 1))
        self.reward_spec = Unbounded((n, 1))
        self.count = torch.zeros(n, dtype=torch.long)

    def _obs(self):
        return torch.stack([self.count.float(), torch.ones(self.batch_size)], -1)

    def _reset(self, td):
        mask = torch.ones(self.batch_size, dtype=torch.bool)
        if td is not None and "_reset" in td:
            mask = td["_reset"].reshape(-1)
        self.count[mask] = 0
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(observation=self._obs(), done=done, terminated=done.clone(), batch_size=self.batch_size)

    def _step(self, td):
        self.count += 1
        done = (self.count >= self.lengths).unsqueeze(-1)
        return TensorDict(
            observation=self._obs(), reward=torch.zeros(*self.batch_size, 1), done=done, terminated=done.clone(), batch_size=self.batch_size
        )

    def _set_seed(self, seed):
        return seed


def _rollout_env(actor, lengths=(3, 5, 7)):
    return TransformedEnv(EpisodesOfDifferentLengths(list(lengths)), Compose(*actor.make_transforms()))


def _check_carry(td):
    """option constant within episodes when beta ~ 0; re-picked at every episode start."""
    is_init = td["is_init"].squeeze(-1)
    assert (td["option_start"] == is_init).all()
    # the carry itself: at a non-initial step, the env hands back the option of the step before
    cont = ~is_init[..., 1:]
    assert (td["prev_option"][..., 1:][cont] == td["option"][..., :-1][cont]).all()
    assert (td["termination_prob"][is_init] == 1).all()


def test_option_carried_and_repicked_after_partial_resets():
    torch.manual_seed(0)
    # beta ~ 0; option 0 (the primer's reset value) is never picked, so a lost carry would show
    heads = _constant_heads([-30.0, 0.0, 0.0, 0.0], [[0.0]] * 4, [[0.0]] * 4, [-30.0] * 4)
    actor = OptionCriticActor(heads)
    env = _rollout_env(actor)
    check_env_specs(env)
    td = env.rollout(40, actor, break_when_any_done=False)  # [3, 40]
    _check_carry(td)
    starts = td["is_init"].squeeze(-1)
    # env i restarts every lengths[i] steps: 40/3 -> 14 starts, 40/5 -> 8, 40/7 -> 6
    assert starts.sum(-1).tolist() == [14, 8, 6]
    # uniform pi_O: episodes do pick different options
    assert td["option"][starts].unique().numel() > 1
    # within an episode of env 2 (length 7) the option never changes
    ep = td["option"][2, :7]
    assert (ep == ep[0]).all()


def test_option_terminates_every_step_when_beta_is_one():
    heads = _constant_heads([0.0, 0.0], [[0.0]] * 2, [[0.0]] * 2, [30.0, 30.0])
    actor = OptionCriticActor(heads)
    td = _rollout_env(actor).rollout(20, actor, break_when_any_done=False)
    assert td["option_start"].all()
    assert torch.allclose(td["termination_prob"], torch.ones(()))


def test_option_carry_across_collector_batches():
    from torchrl.collectors import Collector

    torch.manual_seed(1)
    heads = _constant_heads([-30.0, 0.0, 0.0], [[0.0]] * 3, [[0.0]] * 3, [-30.0] * 3)  # never option 0
    actor = OptionCriticActor(heads)
    collector = Collector(_rollout_env(actor, (4, 9)), actor, frames_per_batch=2 * 6, total_frames=2 * 24, split_trajs=False)
    batches = [b.clone() for b in collector]
    collector.shutdown()
    td = torch.cat(batches, -1)
    _check_carry(td)
    # batch boundaries at t = 6, 12, 18 are not episode starts for env 1 at t=6: the option carries over
    assert not td["is_init"][1, 6] and td["prev_option"][1, 6] == td["option"][1, 5] != 0
    assert (td["option"] != 0).all()


def test_deterministic_mode_takes_most_likely_option_and_mean_action():
    heads = _constant_heads([0.0, 2.0, -1.0], [[0.1], [0.3], [-0.2]], [[0.0]] * 3, [-30.0] * 3)
    actor = OptionCriticActor(heads, low=-2.0, high=2.0)
    env = _rollout_env(actor, (5, 5))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(6, actor, break_when_any_done=False)
    assert (td["option"] == 1).all()
    torch.testing.assert_close(td["action"], torch.full_like(td["action"], 2.0 * math.tanh(0.3)))


def test_actor_without_transforms_says_what_to_do():
    actor = OptionCriticActor(OptionHeads(2, 1, 2, hidden=(4,)))
    with pytest.raises(KeyError, match="make_transforms"):
        actor(TensorDict(observation=torch.zeros(3, 2), batch_size=[3]))


def test_moc_learns_a_bandit():
    """End to end on a one-step task: reward = -(a - 0.5)^2 for every option; the loss must move the actions to 0.5."""
    torch.manual_seed(0)
    heads = OptionHeads(2, 1, 2, hidden=(16,), init_log_std=-0.5)
    actor = OptionCriticActor(heads)
    critic = make_option_critic(2, 2, hidden=(16,))
    loss = OptionCriticLoss(actor, critic, eta=0.7)
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    env = _rollout_env(actor, [1] * 64)
    first = None
    for it in range(60):
        with torch.no_grad():
            td = env.rollout(1, actor, break_when_any_done=False)
            a = td["action"].squeeze(-1)
            td["next", "reward"] = -(a - 0.5).pow(2).unsqueeze(-1)
        first = first if first is not None else float(td["next", "reward"].mean())
        loss.value_estimator(td)
        for _ in range(4):
            out = loss(td.reshape(-1))
            opt.zero_grad()
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            opt.step()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(1, actor, break_when_any_done=False)
    assert first < -0.15
    assert (td["action"] - 0.5).abs().max() < 0.1


@pytest.mark.parametrize("normalize", [False, True])
def test_termination_advantage_normalisation_is_scale_free(normalize):
    """Normalised: the termination loss does not change when returns are 100x larger; raw: it scales with them."""
    heads = _constant_heads([0.0, 0.0], [[0.0], [0.0]], [[0.0]] * 2, [0.0, 0.0])
    batch = _batch([0.1, 0.1, 0.1], [0, 1, 0], [0, 1, 1], [False, False, False], [[0.0, 0.0]] * 3, [[0.5, 0.5]] * 3, [0.0] * 3, [0.0] * 3)
    values = []
    for scale in (1.0, 100.0):
        loss = OptionCriticLoss(
            OptionCriticActor(heads), _constant_critic([1.0 * scale, 3.0 * scale]), xi=0.01, normalize_option_advantages=normalize
        )
        values.append(loss(batch)["loss_termination"].item())
    # Q - V for prev options (0, 1, 1): -1, +1, +1 (x scale); beta = 0.5
    raw = [0.5 * ((-1 + 1 + 1) * s / 3 + 0.01) for s in (1.0, 100.0)]
    if normalize:  # the std of Q(s, o) - V(s) over the batch and both options: (-1, 1) three times
        std = torch.tensor([-1.0, 1.0] * 3).std().item()
        assert values[0] == pytest.approx(values[1]) == pytest.approx(0.5 * ((1 / 3) / std + 0.01))
    else:
        assert values == pytest.approx(raw)


# ------------------------------------------------- keys, terms, duck typing
def _assert_same(a, b, keys=None):
    """Entries equal bit for bit (NaN == NaN)."""
    for key in keys if keys is not None else a.keys():
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True, msg=lambda m, key=key: f"{key}: {m}")


RENAMED = dict(
    option="my_option",
    prev_option=("carry", "prev"),
    is_init="first_step",
    option_start="my_start",
    termination_prob="my_beta_prev",
    option_log_probs=("logp", "all"),
    assignment_log_prob=("logp", "assign"),
    option_logits="my_logits",
    option_loc=("heads", "loc"),
    option_scale=("heads", "scale"),
    termination_probs=("heads", "beta"),
)
DEFAULT_NAMES = {name: getattr(OptionCriticActor.default_keys(), name) for name in RENAMED}


def test_tensordict_keys_renamed_on_actor_and_loss():
    """Renamed keys on both sides: the same rollout and bit-identical loss values as with the default keys."""
    torch.manual_seed(0)
    heads = OptionHeads(2, 1, 3, hidden=(8,))
    critic = make_option_critic(2, 3, hidden=(8,))
    renamed_critic = make_option_critic(2, 3, hidden=(8,), out_key="my_q")
    renamed_critic.load_state_dict(critic.state_dict())
    results = []
    for rename in (False, True):
        actor = OptionCriticActor(heads)
        if rename:
            actor.set_keys(**RENAMED)
            assert actor.tensor_keys.option == "my_option" and actor.in_keys[1] == ("carry", "prev")
        torch.manual_seed(1)
        with torch.no_grad():
            td = _rollout_env(actor).rollout(8, actor, break_when_any_done=False)
        loss = OptionCriticLoss(actor, renamed_critic if rename else critic, eta=0.5, xi=0.01, entropy_coef=0.01)
        if rename:
            # the loss took the actor's and critic's names; setting them (and the estimator's) explicitly is the same
            assert loss.tensor_keys.prev_option == ("carry", "prev") and loss.tensor_keys.option_value == "my_q"
            loss.set_keys(**RENAMED, option_value="my_q", advantage="my_adv", value_target=("gae", "target"))
        loss.value_estimator(td)
        torch.manual_seed(2)
        results.append((td, loss(td.reshape(-1))))
    (td, out), (td_r, out_r) = results
    assert "option" not in td_r.keys() and "is_init" not in td_r.keys() and "advantage" not in td_r.keys()
    for name, new in RENAMED.items():
        if name in ("option_logits", "option_loc", "option_scale", "termination_probs"):
            continue  # written by get_option_heads in the loss's copy, not into the rollout
        _assert_same({name: td[DEFAULT_NAMES[name]]}, {name: td_r[new]})
    _assert_same({"a": td["advantage"], "t": td["value_target"]}, {"a": td_r["my_adv"], "t": td_r["gae", "target"]})
    assert (td_r["next", "carry", "prev"] == td_r["my_option"]).all()
    assert set(out.keys()) == set(out_r.keys())
    _assert_same(out, out_r)


def test_actor_set_keys_validates():
    actor = OptionCriticActor(OptionHeads(2, 1, 2, hidden=(4,)))
    with pytest.raises(ValueError, match="not a key"):
        actor.set_keys(opt="o")
    with pytest.raises(ValueError, match="distinct"):
        actor.set_keys(option="prev_option")
    with pytest.raises(ValueError, match="is_init"):
        actor.set_keys(is_init=("a", "b")).make_transforms()
    actor.set_keys(is_init=None)  # back to the default
    assert actor.tensor_keys.is_init == "is_init"


class _ZeroTermination(OptionCriticLoss):
    def termination_loss(self, td):
        losses, metrics = super().termination_loss(td)
        return {"loss_termination": losses["loss_termination"] * 0.0}, metrics


class _DeliberationCost(OptionCriticLoss):
    """Option-Critic's constant deliberation cost on top of the MOC termination term."""

    cost = 0.25

    def termination_loss(self, td):
        losses, metrics = super().termination_loss(td)
        k = self.tensor_keys
        beta = td.get(k.termination_probs).gather(-1, td.get(k.prev_option).long().reshape(-1, 1)).squeeze(-1)
        cont = ~td.get(k.is_init).reshape(-1).bool()
        return {"loss_termination": losses["loss_termination"] + self.cost * beta[cont].mean()}, metrics


@pytest.mark.parametrize("subclass", [_ZeroTermination, _DeliberationCost])
def test_overriding_the_termination_term_changes_only_loss_termination(subclass):
    torch.manual_seed(0)
    heads = OptionHeads(2, 1, 3, hidden=(8,))
    critic = make_option_critic(2, 3, hidden=(8,))
    actor = OptionCriticActor(heads)
    with torch.no_grad():
        td = _rollout_env(actor).rollout(10, actor, break_when_any_done=False)
    outs, grads = [], []
    for cls in (OptionCriticLoss, subclass):
        loss = cls(actor, critic, eta=0.7, xi=0.05)
        loss.value_estimator(td)
        torch.manual_seed(3)
        out = loss(td.reshape(-1))
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        outs.append(out)
        grads.append(loss.actor_network_params["heads", "termination_head", "2", "weight"].grad.clone())
        heads.zero_grad()
    base, sub = outs
    assert list(base.keys()) == list(sub.keys())
    _assert_same(base, sub, [k for k in base.keys() if k != "loss_termination"])
    cont = ~td["is_init"].reshape(-1)
    if subclass is _ZeroTermination:
        assert base["loss_termination"] != 0 and sub["loss_termination"] == 0
        assert (grads[0] != 0).any() and (grads[1] == 0).all()  # beta learns from this term only
    else:
        with torch.no_grad():
            beta = heads(td["observation"].reshape(-1, 2))[3].gather(-1, td["prev_option"].reshape(-1, 1)).squeeze(-1)
        torch.testing.assert_close(sub["loss_termination"], base["loss_termination"] + 0.25 * beta[cont].mean())


class _PlainOptionActor(torch.nn.Module):
    """Not an OptionCriticActor: just the two methods (and num_options) the loss needs."""

    def __init__(self, heads, with_dist=True):
        super().__init__()
        self.heads = heads
        self.num_options = heads.num_options
        if not with_dist:
            self.get_dist = None

    def get_option_heads(self, td):
        logits, loc, scale, beta = self.heads(td["observation"])
        td.update({"option_logits": logits, "option_loc": loc, "option_scale": scale, "termination_probs": beta})
        return td

    def get_dist(self, td):
        from torchrl.modules import TanhNormal

        return TanhNormal(td["option_loc"], td["option_scale"], low=-torch.ones(1), high=torch.ones(1), safe_tanh=True)


def test_loss_accepts_a_duck_typed_actor_and_names_a_missing_method():
    loss, batch, _new, _old = _loss_setup(1.0, old_shift=0.1)
    heads = loss.actor_network.heads
    duck = OptionCriticLoss(_PlainOptionActor(heads), _constant_critic([0.0, 0.0, 0.0]), eta=1.0, clip_epsilon=0.2, normalize_advantage=False)
    _assert_same(loss(batch), duck(batch))
    with pytest.raises(TypeError, match="get_dist"):
        OptionCriticLoss(_PlainOptionActor(heads, with_dist=False), _constant_critic([0.0, 0.0, 0.0]))
    with pytest.raises(TypeError, match="get_option_heads"):
        OptionCriticLoss(torch.nn.Linear(2, 3), _constant_critic([0.0, 0.0, 0.0]), num_options=3)
    with pytest.raises(TypeError, match="Module"):
        OptionCriticLoss(object(), _constant_critic([0.0, 0.0, 0.0]))
    no_count = _PlainOptionActor(heads)
    del no_count.num_options
    with pytest.raises(TypeError, match="num_options"):
        OptionCriticLoss(no_count, _constant_critic([0.0, 0.0, 0.0]))
    assert OptionCriticLoss(no_count, _constant_critic([0.0, 0.0, 0.0]), num_options=3).num_options == 3


def test_option_gae_renamed_keys_write_the_same_values():
    from torchrl.objectives.value import ValueEstimatorBase

    torch.manual_seed(0)
    actor = OptionCriticActor(OptionHeads(2, 1, 3, hidden=(8,)))
    loss = OptionCriticLoss(actor, make_option_critic(2, 3, hidden=(8,)))
    with torch.no_grad():
        td = _rollout_env(actor).rollout(9, actor, break_when_any_done=False)
    gae = loss.value_estimator
    assert isinstance(gae, ValueEstimatorBase) and gae.out_keys == ["advantage", "value_target"]
    ref = gae(td.clone())
    keys_before = set(td.keys(True))
    gae.set_keys(advantage="my_adv", value_target=("gae", "target"))
    assert gae.tensor_keys.advantage == "my_adv" and gae.out_keys == ["my_adv", ("gae", "target")]
    out = gae(td)
    assert out is td and "advantage" not in td.keys() and "value_target" not in td.keys()
    assert set(td.keys(True)) - keys_before == {"my_adv", ("gae", "target"), "gae"}  # no heads or Q written
    _assert_same({"a": ref["advantage"], "t": ref["value_target"]}, {"a": td["my_adv"], "t": td["gae", "target"]})
    _assert_same({"t": ref["value_target"]}, {"t": gae.value_estimate(td)})
    # keys set on the loss are forwarded to its estimator
    loss.set_keys(advantage="adv2", value_target="target2")
    assert loss.value_estimator.tensor_keys.advantage == "adv2"
    loss.value_estimator(td)
    _assert_same({"a": ref["advantage"], "t": ref["value_target"]}, {"a": td["adv2"], "t": td["target2"]})
