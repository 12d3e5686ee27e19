"""The agent layer: registry, configs, and a new algorithm added from a test file without touching the library."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import LossModule

from torchrl_offhrl.agents import AGENTS, Agent, agent_defaults, make_agent, register_agent
from torchrl_offhrl.nets import tanh_gaussian_actor

ROOT = Path(__file__).resolve().parents[1]


class MeanRewardLoss(LossModule):
    """A toy REINFORCE loss: ``-mean(log pi(a|s) * (r - mean r))`` on one-step rewards."""

    def __init__(self, actor, action_key):
        super().__init__()
        self.actor = actor
        self.action_key = action_key

    def forward(self, td):
        dist = self.actor.get_dist(td.select("observation"))
        logp = dist.log_prob(td[self.action_key])
        r = td["next", "reward"].squeeze(-1)
        adv = r - r.mean()
        return {"loss_pg": -(logp * adv).mean(), "mean_reward": r.mean().detach()}


class ToyAgent(Agent):
    """A state-independent tanh-Gaussian in the latent box, trained by one REINFORCE step per batch."""

    evaluation_files = ("toy.txt",)

    def __init__(self, env, *, obs_loc=None, obs_scale=None, action_key="latent_action", device="cpu", lr: float = 0.05, frames_per_batch: int = 64):
        act_dim = env.full_action_spec[action_key].shape[-1]
        box = env.full_action_spec[action_key].space
        net = nn.Sequential(nn.Linear(env.observation_spec["observation"].shape[-1], 2 * act_dim))
        from tensordict.nn import NormalParamExtractor

        module = TensorDictModule(nn.Sequential(net, NormalParamExtractor()), ["observation"], ["loc", "scale"])
        self.policy = tanh_gaussian_actor(module, box.low.reshape(-1, act_dim)[0], box.high.reshape(-1, act_dim)[0], action_key)
        self.loss = MeanRewardLoss(self.policy, action_key)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.frames_per_batch = frames_per_batch
        self.batches_seen: list[tuple] = []

    def update(self, batch):
        self.batches_seen.append((tuple(batch.batch_size), sorted(map(str, batch.keys(True, True)))))
        out = self.loss(batch.reshape(-1))
        self.optimizer.zero_grad()
        out["loss_pg"].backward()
        self.optimizer.step()
        return {"train/mean_reward": float(out["mean_reward"]), "updates": 1}

    def evaluation_metrics(self, rollout, alive):
        return {"toy_steps_alive": int(alive.sum())}

    def save_evaluation(self, rollout, alive, run_dir, title):
        (Path(run_dir) / "toy.txt").write_text(f"{title}: {int(alive.sum())} steps\n")


@pytest.fixture
def toy_registered():
    register_agent("toy-pg")(ToyAgent)
    yield ToyAgent
    AGENTS.pop("toy-pg")


def test_a_new_agent_trains_end_to_end_without_library_changes(toy_registered, hopper_file, tmp_path, monkeypatch):
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    cfg = to_plain(compose("offline_train", [
        f"dataset={hopper_file}", f"out_root={tmp_path}", "ensemble.hidden_sizes=[32,32]", "ensemble.fit.max_steps=40",
        "cvae.hidden_sizes=[32,32]", "cvae.fit.max_steps=40", "collector.num_envs=4", "train.total_frames=256",
        "eval.every_frames=128", "eval.episodes=2", "eval.max_steps=40",
    ]))
    cfg["algo"] = {"name": "toy-pg", "lr": 0.05, "frames_per_batch": 64}  # no configs/algo/toy-pg.yaml needed either
    seen = {}
    real = ToyAgent.update

    def spy(self, batch):
        seen["agent"] = self
        seen.setdefault("before", [p.detach().clone() for p in self.loss.parameters()])
        return real(self, batch)

    monkeypatch.setattr(ToyAgent, "update", spy)
    summary = train(cfg, progress=False)
    run = Path(summary["run_dir"])
    assert run.name.startswith("toy-pg-hopper-")
    agent = seen["agent"]
    # the loop fed it 4 batches of [4 envs, 16 steps] from the composed env, with the latent action and the model's reward
    assert [b[0] for b in agent.batches_seen] == [(4, 16)] * 4
    assert {"latent_action", "action", "('next', 'reward')", "('next', 'penalized')"} <= set(agent.batches_seen[0][1])
    assert summary["frames"] == 256 and summary["updates"] == 4
    # it learned: the parameters moved
    assert any(not torch.equal(a, b) for a, b in zip(seen["before"], agent.loss.parameters()))
    evals = json.loads((run / "evals.json").read_text())
    assert [e["frames"] for e in evals] == [0, 128, 256]
    assert all(0 < e["toy_steps_alive"] <= 2 * 40 for e in evals)  # 2 episodes of at most 40 steps
    # the same policy in the model env: the model-real gap is the difference of the two means
    assert all(e["model_real_gap"] == pytest.approx(e["model_return_mean"] - e["return_mean"]) for e in evals)
    assert (run / "training_metrics.png").stat().st_size > 1000
    assert (run / "toy.txt").read_text().startswith("Hopper-v5, ")
    assert str(run / "toy.txt") not in summary["plots"] and summary["plots"] == [str(run / "learning_curve.png")]


def test_make_agent_rejects_unknown_names_and_keys():
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=8)
    with pytest.raises(ValueError, match=r"unknown algorithm 'td4'; registered agents: \['bc', 'cql', 'iql', 'moc', 'mopo', 'ppo', 'sac', 'sac_her', 'td3bc', 'uof'"):
        make_agent("td4", env)
    with pytest.raises(TypeError, match=r"algo=moc: unknown hyper-parameter\(s\) \['etaa'\]; MOCAgent accepts \[.*'eta'"):
        make_agent("moc", env, {"etaa": 0.5})
    agent = make_agent("MOC", env, {"name": "moc", "num_options": 3}, epochs=1)
    assert agent.name == "moc" and agent.num_options == 3 and agent.epochs == 1
    with pytest.raises(ValueError, match="already registered"):
        register_agent("moc")(ToyAgent)


@pytest.mark.parametrize("config", sorted(p.stem for p in (ROOT / "configs" / "algo").glob("*.yaml")))
def test_algo_configs_match_their_agents(config):
    """Each configs/algo/*.yaml lists exactly the hyper-parameters its agent takes: no typo is silently ignored."""
    from torchrl_offhrl.recipes.config import compose

    cfg = dict(compose("offline_train", [f"algo={config}"]).algo)
    name = cfg.pop("name")
    assert cfg.pop("label", name) == config  # a variant of an agent names its runs after its config
    assert sorted(cfg) == sorted(agent_defaults(name))


def test_off_policy_agent_waits_for_its_random_frames():
    """SAC steps no gradient before init_random_frames frames were collected, then utd_ratio steps per frame."""
    from tensordict import TensorDict

    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=8)
    agent = make_agent("sac", env, init_random_frames=48, utd_ratio=0.25, batch_size=8, buffer_size=100, hidden_sizes=[8])
    with torch.no_grad():
        batch = env.rollout(4, agent.policy, break_when_any_done=False)  # [8 envs, 4 steps] = 32 frames
    assert isinstance(batch, TensorDict) and batch.numel() == 32
    assert agent.update(batch)["updates"] == 0 and len(agent.replay_buffer) == 32
    assert agent.update(batch)["updates"] == 8 and len(agent.replay_buffer) == 64  # 64 >= 48: 32 frames x 0.25
    agent2 = make_agent("sac", env, init_random_frames=48, utd_ratio=0.25, batch_size=8, buffer_size=100, hidden_sizes=[8])
    agent2.load_state_dict(agent.state_dict())
    assert agent2.frames == 64
    for a, b in zip(agent.loss.parameters(), agent2.loss.parameters()):
        assert torch.equal(a, b)



def test_reward_scale_scales_what_the_agent_learns_from_only(toy_registered, hopper_file, tmp_path, monkeypatch):
    """model_env.reward_scale=0.5 halves the rewards in the agent's batches; the logged episode returns stay unscaled."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    seen = []
    real = ToyAgent.update
    monkeypatch.setattr(ToyAgent, "update", lambda self, batch: (seen.append(batch.clone()), real(self, batch))[1])
    for scale in (1.0, 0.5):
        cfg = to_plain(compose("offline_train", [
            f"dataset={hopper_file}", f"out_root={tmp_path / str(scale)}", "ensemble.hidden_sizes=[32,32]", "ensemble.fit.max_steps=40",
            "cvae.hidden_sizes=[32,32]", "cvae.fit.max_steps=40", "collector.num_envs=4", "train.total_frames=64",
            "eval.every_frames=64", "eval.episodes=2", "eval.max_steps=10", "eval.at_start=false", "eval.model_env=false",
            f"model_env.reward_scale={scale}",
        ]))
        cfg["algo"] = {"name": "toy-pg", "frames_per_batch": 64}
        train(cfg, progress=False)
    full, half = seen
    torch.testing.assert_close(full["next", "observation"], half["next", "observation"])  # the same rollout
    torch.testing.assert_close(half["next", "reward"], 0.5 * full["next", "reward"])
    torch.testing.assert_close(half["next", "episode_reward"], full["next", "episode_reward"])
    assert full["next", "episode_reward"].abs().sum() > 0


@pytest.mark.parametrize("algo", ["ppo", "moc"])
def test_speed_switches_do_not_change_the_update(algo):
    """fused_adam and (PPO) functional are speed switches: one on-policy update gives the same parameters either way."""
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=8)
    common = {"hidden_sizes": [8], "frames_per_batch": 32, "minibatch_size": 8, "epochs": 2}
    slow = {"fused_adam": False, **({"functional": True} if algo == "ppo" else {})}
    fast = {"fused_adam": True, **({"functional": False} if algo == "ppo" else {})}
    agents = []
    for switches in (slow, fast):
        torch.manual_seed(0)
        agents.append(make_agent(algo, env, **common, **switches))
        agents[-1].attach(env)
    def weights(agent):  # the functional loss keeps its copies under "<net>_params."
        return {k.replace("_params.", "."): v for k, v in agent.loss.state_dict().items()}

    start = {k: v.clone() for k, v in weights(agents[0]).items()}
    for name, a in start.items():  # built from the same seed: the same start
        assert torch.equal(a, weights(agents[1])[name]), name
    torch.manual_seed(1)
    env.set_seed(1)
    with torch.no_grad():
        batch = env.rollout(4, agents[0].policy, break_when_any_done=False)
    metrics = []
    for agent in agents:
        torch.manual_seed(2)  # the same minibatch order
        metrics.append(agent.update(batch.clone()))
    assert metrics[0]["updates"] == metrics[1]["updates"] == 8
    after = [weights(a) for a in agents]
    assert after[0].keys() == after[1].keys()
    assert any(not torch.equal(v, start[k]) for k, v in after[0].items())  # the update moved the weights
    for name, a in after[0].items():
        torch.testing.assert_close(a, after[1][name], rtol=1e-4, atol=1e-5, msg=name)
    for k in ("train/loss_objective", "train/loss_critic"):
        assert metrics[0][k] == pytest.approx(metrics[1][k], rel=1e-4, abs=1e-6)


def test_anneal_lr_follows_the_frame_budget():
    """anneal_lr: every optimiser's lr is its initial lr x (1 - fraction done), MOC's termination and pi_O optimisers too; off: unchanged."""
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=8)
    moc = make_agent("moc", env, hidden_sizes=[8], lr=1e-4, termination_lr=1e-3, option_lr=2e-3, anneal_lr=True)
    assert len(moc.optimizers()) == 3
    moc.set_progress(0.25)
    lrs = sorted(g["lr"] for opt in moc.optimizers() for g in opt.param_groups)
    assert lrs == pytest.approx([0.75e-4, 0.75e-3, 1.5e-3])
    moc.set_progress(1.0)
    assert all(g["lr"] == 0.0 for opt in moc.optimizers() for g in opt.param_groups)
    moc.set_progress(0.5)  # from the initial lr, not compounded
    assert sorted(g["lr"] for opt in moc.optimizers() for g in opt.param_groups) == pytest.approx([0.5e-4, 0.5e-3, 1e-3])
    ppo = make_agent("ppo", env, hidden_sizes=[8], lr=3e-4)
    ppo.set_progress(0.5)
    assert all(g["lr"] == 3e-4 for g in ppo.optimizer.param_groups)


def test_training_loop_reports_progress_before_each_update(toy_registered, hopper_file, tmp_path, monkeypatch):
    """train() calls agent.set_progress(frames done / total) before every update: 0 and 0.5 for two batches of 64 out of 128."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    seen = []
    monkeypatch.setattr(ToyAgent, "set_progress", lambda self, f: seen.append(f), raising=False)
    cfg = to_plain(compose("offline_train", [
        f"dataset={hopper_file}", f"out_root={tmp_path}", "ensemble.hidden_sizes=[32,32]", "ensemble.fit.max_steps=40",
        "cvae.hidden_sizes=[32,32]", "cvae.fit.max_steps=40", "collector.num_envs=4", "train.total_frames=128",
        "eval.every_frames=128", "eval.episodes=2", "eval.max_steps=10", "eval.at_start=false", "eval.model_env=false",
    ]))
    cfg["algo"] = {"name": "toy-pg", "frames_per_batch": 64}
    train(cfg, progress=False)
    assert seen == [0.0, 0.5]


def test_moc_option_kl_and_starts_hand_computed():
    """option_kl: mean KL between options' Gaussians at the visited states (|mu_i - mu_j|^2 / 2 at unit scale); one option: 0."""
    from tensordict import TensorDict

    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=4)
    moc = make_agent("moc", env, hidden_sizes=[8], num_options=2, init_log_std=0.0)
    last = moc.policy.heads.intra_head[-1]
    with torch.no_grad():  # option 0's pre-tanh means are 0, option 1's are 1 and 2 (A = 2), whatever the state
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.0, 0.0, 1.0, 2.0]))
    E, T = 2, 3
    alive = torch.tensor([[True, True, True], [True, True, False]])
    td = TensorDict({"observation": torch.randn(E, T, d.observation_dim), "option": torch.tensor([[0, 1, 1], [1, 1, 0]]),
                     "option_start": torch.tensor([[True, True, False], [True, False, True]])}, [E, T])
    m = moc.evaluation_metrics(td, alive)
    assert m["option_kl"] == pytest.approx((1.0 + 4.0) / 2)  # both ordered pairs: KL symmetric at equal scales
    assert m["option_starts"] == pytest.approx((1 + 0) / 2)  # the dead step's start does not count, nor the first step's
    assert m["option_usage_mean"] == pytest.approx([1 / 5, 4 / 5])
    one = make_agent("moc", env, hidden_sizes=[8], num_options=1)
    assert one.evaluation_metrics(td.set("option", torch.zeros(E, T, dtype=torch.long)), alive)["option_kl"] == 0.0


def test_an_agent_naming_its_losss_hyperparameters_takes_those_with_the_losss_defaults_unless_it_deviates():
    """IQL's config keys for its loss are the ones it names, with IQLLoss's defaults unless ``loss_defaults`` differs;
    a name the loss does not take is refused, and the built loss holds what the config asked for."""
    from torchrl.objectives import IQLLoss

    from torchrl_offhrl.agents.registry import loss_arguments
    from torchrl_offhrl.data import make_gym_env

    agent_cls = AGENTS["iql"]
    assert loss_arguments(agent_cls) == {"expectile": 0.7, "temperature": 3.0, "loss_function": "l2"}
    assert "reduction" not in agent_defaults("iql") and agent_defaults("iql")["expectile"] == 0.7

    class Typo(agent_cls):
        loss_hyperparameters = ("expectile", "temperture")

    with pytest.raises(TypeError, match=r"names \['temperture'\], which SharedPassIQLLoss does not take"):
        loss_arguments(Typo)
    agent = make_agent("iql", make_gym_env("Pendulum-v1"), {"expectile": 0.9, "hidden_sizes": [8]})
    assert isinstance(agent.loss, IQLLoss) and agent.loss.expectile == 0.9 and agent.loss.temperature == 3.0


def test_ppo_and_sac_pass_their_losss_hyperparameters_under_the_losss_names():
    """PPO's coefficients and trust region reach TorchRL's loss as it names them (Stable-Baselines3's vf_coef / ent_coef
    are critic_coeff / entropy_coeff), the knob of the loss the run does not train is left out, a name no loss takes is
    the loss's TypeError; SAC's alpha_init reaches SACLoss (log alpha = log alpha_init)."""
    import math

    from torchrl.objectives import ClipPPOLoss, KLPENPPOLoss

    from torchrl_offhrl.agents.registry import loss_arguments, loss_kwargs_for
    from torchrl_offhrl.data import make_gym_env

    ppo = AGENTS["ppo"]
    assert loss_arguments(ppo) == {"clip_epsilon": 0.2, "dtarg": 0.01, "entropy_coeff": 0.0, "critic_coeff": 0.5}
    assert loss_arguments(ppo, ClipPPOLoss) == {"clip_epsilon": 0.2, "entropy_coeff": 0.0, "critic_coeff": 0.5}
    # the KL penalty's target is not given to the clipped loss, nor the clip to the KL penalty; an unknown name goes on
    assert loss_kwargs_for(ppo, ClipPPOLoss, {"dtarg": 0.5, "clip_epsilon": 0.1}) == {"clip_epsilon": 0.1, "entropy_coeff": 0.0,
                                                                                      "critic_coeff": 0.5}
    assert loss_kwargs_for(ppo, ppo.loss_classes["kl"], {"clip_epsilon": 0.1, "beta_typo": 1})["beta_typo"] == 1
    env = make_gym_env("Pendulum-v1")
    clip = make_agent("ppo", env, {"hidden_sizes": [8], "clip_epsilon": 0.1, "critic_coeff": 0.8, "entropy_coeff": 0.002, "dtarg": 0.5},
                      action_key="action")
    assert type(clip.loss) is ClipPPOLoss
    assert (float(clip.loss.clip_epsilon), float(clip.loss.critic_coeff)) == pytest.approx((0.1, 0.8))
    assert float(clip.loss.entropy_coeff) == pytest.approx(0.002)
    kl = make_agent("ppo", env, {"hidden_sizes": [8], "loss_type": "kl", "dtarg": 0.03, "clip_epsilon": 0.1}, action_key="action")
    assert isinstance(kl.loss, KLPENPPOLoss) and kl.loss.dtarg == pytest.approx(0.03)
    with pytest.raises(TypeError, match="beta_typo"):
        make_agent("ppo", env, {"hidden_sizes": [8], "loss_type": "kl", "beta_typo": 1.0}, action_key="action")
    assert "alpha_init" in agent_defaults("sac") and "alpha_init" in agent_defaults("mopo") and "alpha_init" in agent_defaults("sac_her")
    sac = make_agent("sac", env, {"hidden_sizes": [8], "alpha_init": 0.2}, action_key="action")
    assert float(sac.loss.log_alpha.detach()) == pytest.approx(math.log(0.2))


def test_a_run_written_under_ppos_old_key_names_reads_and_fingerprints_as_today():
    """config.json files written before PPO took its loss's names (vf_coef, ent_coef, kl_target) are read under the new
    names, and fingerprint as the same run (so they resume and archive as before); other values are untouched."""
    from torchrl_offhrl.recipes.config import config_fingerprint, upgrade_config

    old = {"algo": {"name": "ppo", "vf_coef": 0.8, "ent_coef": 0.002, "kl_target": 0.01, "lr": 1e-4}, "seed": 3}
    new = {"algo": {"name": "ppo", "critic_coeff": 0.8, "entropy_coeff": 0.002, "dtarg": 0.01, "lr": 1e-4}, "seed": 3}
    assert upgrade_config(old) == new and old["algo"]["vf_coef"] == 0.8  # the caller's dict is left as it was
    assert config_fingerprint(old) == config_fingerprint(new)
    assert config_fingerprint(old) != config_fingerprint({**new, "algo": {**new["algo"], "critic_coeff": 0.5}})
    from torchrl_offhrl.recipes.schema import validate_config  # an old name on the command line says what it is called now

    with pytest.raises(ValueError, match=r"algo.vf_coef: renamed algo.critic_coeff .*write algo.critic_coeff=0.8"):
        validate_config({"algo": {"name": "ppo", "vf_coef": 0.8}})
    with pytest.raises(ValueError, match=r"algo.critic_coeff: expected a number >= 0, got -1.*\n.*algo.dtarg: expected a number > 0, got 0"):
        validate_config({"algo": {"name": "ppo", "critic_coeff": -1, "dtarg": 0}})  # the renamed keys keep their range checks
    from torchrl_offhrl.recipes.config import compose

    with pytest.raises(ValueError, match=r"algo.ent_coef: renamed algo.entropy_coeff .*write algo.entropy_coeff=0.01"):
        compose("offline_train", ["algo=ppo", "algo.ent_coef=0.01"])


@pytest.mark.parametrize("reduction", ["mean", "none"])
def test_shared_pass_iql_loss_equals_torchrls_iql_loss_and_its_gradients(reduction):
    """The IQL agent's loss computes min Q(s, a) and V(s) once for the actor and value terms: its three losses, the
    entropy it reports and every parameter's gradient equal TorchRL's IQLLoss's on the same minibatch (terminal steps
    included), bit for bit on this CPU; and it runs fewer matrix products."""
    import copy

    from tensordict import TensorDict
    from torch.profiler import profile
    from torchrl.objectives import IQLLoss

    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.objectives import SharedPassIQLLoss

    torch.manual_seed(0)
    agent = make_agent("iql", make_gym_env("Pendulum-v1"), {"hidden_sizes": [16, 16]}, action_key="action")
    assert type(agent.loss) is SharedPassIQLLoss
    kwargs = {"num_qvalue_nets": 2, "expectile": 0.7, "temperature": 3.0, "loss_function": "l2", "reduction": reduction}
    nets = (agent.policy, agent.loss.qvalue_network, agent.loss.value_network)
    ours, theirs = SharedPassIQLLoss(*copy.deepcopy(nets), **kwargs), IQLLoss(*copy.deepcopy(nets), **kwargs)
    theirs.load_state_dict(ours.state_dict())
    for loss in (ours, theirs):
        loss.make_value_estimator(gamma=0.99)
    n = 32
    batch = TensorDict({"observation": torch.randn(n, 3), "action": torch.rand(n, 1) * 4 - 2,
                        "next": {"observation": torch.randn(n, 3), "reward": torch.randn(n, 1),
                                 "done": torch.rand(n, 1) < 0.2, "terminated": torch.rand(n, 1) < 0.2}}, [n])
    out = {name: loss(batch.clone()) for name, loss in (("ours", ours), ("theirs", theirs))}
    for key in ("loss_actor", "loss_qvalue", "loss_value"):
        assert torch.equal(out["ours"][key], out["theirs"][key]), key
        assert out["ours"][key].shape == ((n,) if reduction == "none" else ())
    if reduction == "mean":
        assert torch.equal(out["ours"]["entropy"], out["theirs"]["entropy"])
    for name, loss in (("ours", ours), ("theirs", theirs)):
        sum(out[name][k].sum() for k in ("loss_actor", "loss_qvalue", "loss_value")).backward()
    grads = {name: {k: p.grad for k, p in loss.named_parameters()} for name, loss in (("ours", ours), ("theirs", theirs))}
    assert grads["ours"].keys() == grads["theirs"].keys() and any(g is not None for g in grads["ours"].values())
    for k, g in grads["ours"].items():
        assert (g is None and grads["theirs"][k] is None) or torch.equal(g, grads["theirs"][k]), k
    counts = {}
    for name, loss in (("ours", ours), ("theirs", theirs)):
        with profile() as prof:
            loss(batch.clone())
        counts[name] = sum(e.count for e in prof.key_averages() if e.key in ("aten::bmm", "aten::addmm"))
    assert counts["ours"] < counts["theirs"]  # one twin-critic pass and one value pass fewer
