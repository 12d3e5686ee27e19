"""Model-free offline agents (IQL, CQL, TD3+BC, BC): trained on the dataset itself, evaluated like every agent."""
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.recipes import evaluation as evaluation_mod
from torchrl_offhrl.recipes.config import compose
from torchrl_offhrl.recipes.train import train
from torchrl_offhrl.utils import to_plain
from conftest import load_script
from importlib import import_module

ROOT = Path(__file__).resolve().parents[1]
DATASET_ALGOS = ["bc", "iql", "td3bc", "cql"]
TINY = ["eval.episodes=2", "eval.max_steps=30", "algo.batch_size=16", "algo.hidden_sizes=[16,16]"]
# tiny models and batches for the model-env agents (also tests/test_cuda.py)
TINY_MODEL = ["ensemble.hidden_sizes=[16]", "ensemble.fit.max_steps=20", "cvae.hidden_sizes=[16]", "cvae.fit.max_steps=20",
              "collector.num_envs=4", "algo.frames_per_batch=64", "eval.model_env=false"]
MODEL_EXTRA = {"sac": ["algo.init_random_frames=32", "algo.utd_ratio=0.05"], "ppo": ["algo.epochs=1"], "moc": ["algo.epochs=1"]}


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _cfg(algo, data, out, *extra):
    return to_plain(compose("offline_train", [f"algo={algo}", f"dataset={data}", f"out_root={out}", *TINY, *extra]))


def _params(run_dir):
    return torch.load(Path(run_dir) / "checkpoint.pt", weights_only=True)["agent"]["loss"]


@pytest.mark.parametrize("algo", DATASET_ALGOS)
def test_dataset_agent_trains_end_to_end_without_models(algo, hopper_file, cache, tmp_path):
    summary = train(_cfg(algo, hopper_file, tmp_path, "train.total_updates=40", "eval.every_updates=20"), progress=False)
    run = Path(summary["run_dir"])
    assert run.name.startswith(f"{algo}-hopper-hopper_random-")
    assert summary["unit"] == "updates" and summary["updates"] == summary["step"] == 40
    assert summary["frames"] == 40 * 16  # transitions drawn from the dataset
    evals = json.loads((run / "evals.json").read_text())
    assert [(e["step"], e["updates"]) for e in evals] == [(0, 0), (20, 20), (40, 40)]
    assert all("model_return_mean" not in e for e in evals)  # no model env: no model-real gap
    assert summary["models"] is None and not (cache / "models").exists()  # nothing fitted
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["unit"] == "updates" and cfg["threshold"] is None
    for f in ("checkpoint.pt", "summary.json", "learning_curve.png", "training_metrics.png"):
        assert (run / f).is_file(), f
    # it learned: the trained parameters moved from the untrained agent's
    fresh = train(_cfg(algo, hopper_file, tmp_path / "zero", "train.total_updates=1", "eval.every_updates=1", "eval.at_start=false"), progress=False)
    moved = [k for k, v in _params(fresh["run_dir"]).items() if v.is_floating_point() and "params" in k and not torch.equal(v, _params(run)[k])]
    assert moved


@pytest.mark.fault("resume")
@pytest.mark.parametrize("algo", ["iql", "td3bc"])
def test_an_interrupted_dataset_run_resumes_to_the_same_agent(algo, hopper_file, cache, tmp_path):
    """40 updates then 20 more from the checkpoint give the same networks as 60 in one go (targets, delay counter and sampling RNG restored)."""
    straight = train(_cfg(algo, hopper_file, tmp_path / "a", "train.total_updates=60", "eval.every_updates=20"), progress=False)
    train(_cfg(algo, hopper_file, tmp_path / "b", "train.total_updates=40", "eval.every_updates=20"), progress=False)
    resumed = train(_cfg(algo, hopper_file, tmp_path / "b", "train.total_updates=60", "eval.every_updates=20"), progress=False)
    a, b = _params(straight["run_dir"]), _params(resumed["run_dir"])
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], msg=k)
    evals = json.loads((Path(resumed["run_dir"]) / "evals.json").read_text())
    assert [e["step"] for e in evals] == [0, 20, 40, 60]
    assert [e["return_mean"] for e in evals] == [e["return_mean"] for e in json.loads((Path(straight["run_dir"]) / "evals.json").read_text())]


def test_every_agent_is_evaluated_on_the_same_episodes(hopper_file, cache, tmp_path, monkeypatch):
    """Same config, any algorithm (model env or dataset, latent or real actions): the same evaluation episodes from the same start states.

    (The goal-conditioned agents, which act only on the block-stacking tasks, are evaluated per goal: tests/test_uof.py.)
    """
    from torchrl_offhrl.agents import AGENTS, requires_goal

    flat = sorted(a for a in AGENTS if not requires_goal(a))

    starts: dict[str, list] = {}
    real = evaluation_mod.evaluate_policy

    def spy(env, policy, episodes, **kw):
        out = real(env, policy, episodes, **kw)
        if kw.get("return_rollout"):  # the real-env evaluation (the model-env one does not keep its rollout)
            starts.setdefault(current["algo"], []).append((episodes, kw["max_steps"], kw["seed"], out[1]["observation"][:, 0].clone()))
        return out

    monkeypatch.setattr(evaluation_mod, "evaluate_policy", spy)
    current = {}
    for algo in flat:
        current["algo"] = algo
        overrides = ["train.total_updates=2", "eval.every_updates=2"] if algo in DATASET_ALGOS else [*TINY_MODEL, "train.total_frames=64", "eval.every_frames=64", *MODEL_EXTRA.get(algo, [])]
        train(to_plain(compose("offline_train", [f"algo={algo}", f"dataset={hopper_file}", f"out_root={tmp_path}", "eval.episodes=3",
                                                 "eval.max_steps=15", "algo.hidden_sizes=[16,16]", *overrides])), progress=False)
    assert set(starts) == set(flat) >= {"moc", "ppo", "sac", *DATASET_ALGOS}
    reference = starts["moc"][0]
    for algo, evals in starts.items():
        assert len(evals) == 2, algo  # at the start and at the end
        for episodes, max_steps, seed, obs in evals:
            assert (episodes, max_steps, seed) == reference[:3], algo
            torch.testing.assert_close(obs, reference[3], msg=algo)


def test_return_range_reward_scale_hand_computed():
    from torchrl_offhrl.data import OfflineDataset
    from torchrl_offhrl.recipes.config import resolve_reward_scale, return_range_reward_scale

    # two episodes: returns 1 + 2 = 3 and 4 + 1 = 5 (range 2), 1000 / 2 = 500
    td = TensorDict({"observation": torch.zeros(4, 1), "action": torch.zeros(4, 1), "next": {
        "observation": torch.zeros(4, 1), "reward": torch.tensor([[1.0], [2.0], [4.0], [1.0]]),
        "terminated": torch.tensor([[False], [True], [False], [True]]), "truncated": torch.zeros(4, 1, dtype=torch.bool)}}, batch_size=[4])
    data = OfflineDataset(td)
    assert return_range_reward_scale(data) == pytest.approx(500.0)
    assert resolve_reward_scale("return_range", data) == pytest.approx(500.0)
    assert resolve_reward_scale(0.25, data) == 0.25
    with pytest.raises(ValueError, match="positive number, 'auto' or 'return_range'"):
        resolve_reward_scale("max", data)


def test_dataset_agents_learn_from_scaled_rewards_and_leave_the_batch_alone():
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    agent = make_agent("iql", env, {"reward_scale": 0.5, "hidden_sizes": [8], "batch_size": 4}, action_key="action")
    batch = TensorDict({"observation": torch.zeros(4, 3), "next": {"reward": torch.ones(4, 1)}}, batch_size=[4])
    scaled = agent.scaled(batch)
    torch.testing.assert_close(scaled["next", "reward"], torch.full((4, 1), 0.5))
    torch.testing.assert_close(batch["next", "reward"], torch.ones(4, 1))
    with pytest.raises(ValueError, match="resolved from the data"):
        make_agent("iql", env, {"reward_scale": "return_range"}, action_key="action")


def test_iql_paper_actor_is_a_normal_around_the_squashed_mean_with_one_scale_per_dimension():
    # actor=tanh_mean_gaussian (the IQL paper's): the deterministic action is low + (high - low) (tanh(net) + 1) / 2, the scale
    # exp(log_std) is the same in every state, and the log-likelihood of an action at the box's edge is the Normal's, finite
    # (a tanh-Gaussian takes atanh of it); samples are projected into the box
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")  # action box [-2, 2]
    agent = make_agent("iql", env, {"hidden_sizes": [8], "batch_size": 4, "actor": "tanh_mean_gaussian", "log_std_min": -5.0},
                       action_key="action")
    squashed_mean, scale_mod = agent.policy.module[0].module  # deterministic_actor's MLP and tanh, then the scale
    mean_net = squashed_mean.module[0]
    with torch.no_grad():
        scale_mod.module.state_independent_scale.copy_(torch.tensor([-0.5]))
    obs = torch.randn(6, 3, generator=torch.Generator().manual_seed(0))
    td = TensorDict(observation=obs, batch_size=[6])
    raw = mean_net.module(obs)
    expected_mean = -2 + 4 * (torch.tanh(raw) + 1) / 2
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        torch.testing.assert_close(agent.policy(td.clone())["action"], expected_mean)
    with torch.no_grad():
        dist = agent.policy.get_dist(td.clone())
    torch.testing.assert_close(dist.base_dist.scale, torch.full((6, 1), math.exp(-0.5)))
    edge = torch.full((6, 1), 2.0)
    normal = torch.distributions.Normal(expected_mean, math.exp(-0.5))
    torch.testing.assert_close(dist.log_prob(edge), normal.log_prob(edge).squeeze(-1))
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        scale_mod.module.state_independent_scale.fill_(3.0)  # wide: many raw samples fall outside the box
        sampled = agent.policy(td.expand(200, 6).clone())["action"]
    assert sampled.abs().max() <= 2.0 and (sampled.abs() == 2.0).any()
    with torch.no_grad():  # the floor: log-std -7 gives the scale exp(-5)
        scale_mod.module.state_independent_scale.fill_(-7.0)
        torch.testing.assert_close(agent.policy.get_dist(td.clone()).base_dist.scale, torch.full((6, 1), math.exp(-5.0)))
    with pytest.raises(ValueError, match="tanh_mean_gaussian"):
        make_agent("iql", env, {"hidden_sizes": [8], "actor": "normal"}, action_key="action")


def test_td3bc_steps_its_actor_every_second_update():
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    agent = make_agent("td3bc", env, {"hidden_sizes": [8], "batch_size": 8}, action_key="action")
    td = env.rollout(16, break_when_any_done=False).reshape(-1)
    actor = [p.detach().clone() for p in agent.loss.actor_network_params.flatten_keys().values()]
    first = agent.update(td[:8])
    assert "train/loss_actor" not in first
    assert all(torch.equal(a, p) for a, p in zip(actor, agent.loss.actor_network_params.flatten_keys().values()))
    second = agent.update(td[8:])
    assert "train/loss_actor" in second
    assert any(not torch.equal(a, p) for a, p in zip(actor, agent.loss.actor_network_params.flatten_keys().values()))


def pendulum_agents(algo, switch, values, extra=None, updates=3, batch=8, device="cpu"):
    """One ``algo`` agent on Pendulum per value of config key ``switch``, each from seed 0, each given the same ``updates``
    batches of ``batch`` transitions; returns ``[(agent, [update metrics])]`` (speed switches must give the same agents)."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    td = env.rollout(updates * batch, break_when_any_done=False).reshape(-1).to(device)
    out = []
    for value in values:
        torch.manual_seed(0)
        agent = make_agent(algo, env, {"hidden_sizes": [8], "batch_size": batch, switch: value, **(extra or {})}, action_key="action",
                           device=device)
        out.append((agent, [agent.update(td[batch * k: batch * (k + 1)].clone()) for k in range(updates)]))
    return out


@pytest.mark.parametrize("algo", ["bc", "iql"])
def test_compiled_loss_takes_the_same_update(algo):
    """compile=true (torch.compile of the loss) is a speed switch: BC's and IQL's updates (no sampling inside) match eager ones."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    (eager, _), (comp, _) = pendulum_agents(algo, "compile", (False, True))
    env = make_gym_env("Pendulum-v1")
    assert list(comp.__dict__["_compiled"]) == [None] and "_compiled" not in eager.__dict__
    for (name, a), b in zip(eager.loss.state_dict().items(), comp.loss.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=name)
    torch.manual_seed(0)
    fresh = make_agent(algo, env, {"hidden_sizes": [8], "batch_size": 8}, action_key="action")
    assert any(not torch.equal(a, b) for a, b in zip(fresh.loss.state_dict().values(), eager.loss.state_dict().values()))  # it did learn


def test_compiled_td3bc_compiles_both_of_its_losses():
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    agent = make_agent("td3bc", env, {"hidden_sizes": [8], "batch_size": 8, "compile": True}, action_key="action")
    td = env.rollout(16, break_when_any_done=False).reshape(-1)
    agent.update(td[:8])
    out = agent.update(td[8:])
    assert set(agent.__dict__["_compiled"]) == {"qvalue_loss", "actor_loss"} and torch.isfinite(torch.tensor(out["train/loss_actor"]))
    with pytest.raises(ValueError, match="torch.compile mode"):
        make_agent("td3bc", env, {"hidden_sizes": [8], "compile": "fast"}, action_key="action")


def test_cql_clones_the_behaviour_before_policy_eval_start():
    """CQL's actor follows loss_actor_bc for the first policy_eval_start updates, then loss_actor."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    agent = make_agent("cql", env, {"hidden_sizes": [8], "batch_size": 8, "policy_eval_start": 1}, action_key="action")
    td = env.rollout(16, break_when_any_done=False).reshape(-1)
    assert agent.update(td[:8])["train/bc_phase"] == 1.0
    assert agent.update(td[8:])["train/bc_phase"] == 0.0


def test_dataset_agents_refuse_the_model_env_ablations(hopper_file, cache, tmp_path):
    with pytest.raises(ValueError, match="do not apply"):
        train(_cfg("bc", hopper_file, tmp_path, "ablation.no_cvae=true", "train.total_updates=2"), progress=False)


def test_offline_baseline_example(hopper_file, cache, tmp_path):
    """examples/offline_baseline.py: the same recipe as a script, through hydra's command line."""
    args = [sys.executable, str(ROOT / "examples" / "offline_baseline.py"), "algo=iql", f"dataset={hopper_file}", f"out_root={tmp_path}",
            "train.total_updates=20", "eval.every_updates=10", *TINY]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, env={**os.environ})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "20 updates: real return" in proc.stdout
    run = next(tmp_path.glob("iql-hopper-hopper_random-*-seed0"))
    assert [e["step"] for e in json.loads((run / "evals.json").read_text())] == [0, 10, 20]


def test_aggregate_counts_dataset_runs_in_gradient_steps(tmp_path):
    """A table mixing model-env runs (frames) and dataset runs (updates): each budget in its own unit, best after step 0."""
    import matplotlib.image

    from torchrl_offhrl.recipes.report import aggregate

    for algo, unit, steps, scores in (("moc", "frames", (0, 2048, 4096), (3.0, 5.0, 4.0)), ("iql", "updates", (0, 50, 100), (1.0, 9.0, 7.0))):
        d = tmp_path / f"{algo}-hopper-medium-seed0"
        d.mkdir()
        evals = [{"frames": s * (16 if unit == "updates" else 1), "updates": s, "step": s, "return_mean": 10 * v, "return_std": 0.0,
                  "normalized_d4rl": v} for s, v in zip(steps, scores)]
        (d / "evals.json").write_text(json.dumps(evals))
        (d / "config.json").write_text(json.dumps({"algo": {"name": algo}, "env": {"env_id": "Hopper-v5"}, "dataset": "medium", "ablation": {},
                                                   "unit": unit, "model_env": {"latent_origin": "best"}}))
    table = aggregate(sorted(tmp_path.glob("*-seed0")), tmp_path / "agg")
    # final, last-5 mean (after step 0), selected (none), best, untrained, change over the start
    assert "| iql | Hopper-v5 | medium | - | 1 | 100 updates | 70.0 ± 0.0 | 7.0 | 7.0 ± 0.0 | 8.0 | — | 9.0 | 1.0 | +6.0 [+6.0, +6.0] (1/1) | n/a | s?: 7.0 |" in table
    assert "| moc | Hopper-v5 | medium | - | 1 | 4096 frames | 40.0 ± 0.0 | 4.0 | 4.0 ± 0.0 | 4.5 | — | 5.0 | 3.0 | +1.0 [+1.0, +1.0] (1/1) | n/a | s?: 4.0 |" in table
    height, width = matplotlib.image.imread(tmp_path / "agg" / "curves.png").shape[:2]
    assert height > width  # one row of panels per unit (frames, gradient steps), one column per env


def test_aggregate_keeps_paper_preset_runs_out_of_the_default_row(tmp_path):
    """A model-env run made on the paper's per-dataset settings (latent origin zero, or none recorded: before the offline
    rules) is its own row, ``<algo>_paper``, as in Table I's columns: it never pools with the default's runs of the same
    algorithm. Dataset agents have no preset: their rows keep their label."""
    from torchrl_offhrl.recipes.report import aggregate

    _fake_run(tmp_path, "moc", 4, "Hopper-v5", "medium", "frames", (3.0, 5.0, 4.0))
    paper = _fake_run(tmp_path / "p", "moc", 4, "Hopper-v5", "medium", "frames", (3.0, 5.0, 80.0))
    cfg = json.loads((paper / "config.json").read_text())
    (paper / "config.json").write_text(json.dumps({**cfg, "model_env": {"latent_origin": "zero"}}))
    _fake_run(tmp_path, "iql", 4, "Hopper-v5", "medium", "updates", (1.0, 9.0, 7.0))
    table = aggregate([*sorted(tmp_path.glob("*-seed4")), paper], tmp_path / "agg")
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| ") and "Hopper" in line}
    assert set(rows) == {"moc", "moc_paper", "iql"}
    assert "| 1 |" in rows["moc"] and "s4: 4.0" in rows["moc"] and "s4: 80.0" in rows["moc_paper"]


def _fake_run(base, algo, seed, env_id, dataset, unit, scores, behaviour=None, ablation=None, algo_cfg=None, timing=None, data_hash=None):
    d = base / f"{algo}-{env_id}-{dataset}-seed{seed}"
    d.mkdir(parents=True)
    steps = (0, 100, 200)
    (d / "evals.json").write_text(json.dumps([{"frames": s, "updates": s, "step": s, "return_mean": 10 * v, "return_std": 0.0, "normalized_d4rl": v}
                                              for s, v in zip(steps, scores)]))
    cfg = {"algo": {"name": "ppo" if algo == "morel" else algo, **({"label": "morel"} if algo == "morel" else {}), **(algo_cfg or {})},
           "env": {"env_id": env_id},
           "dataset": dataset, "ablation": ablation or {}, "unit": unit, "seed": seed, **({"data_hash": data_hash} if data_hash else {}),
           "model_env": {"latent_origin": "best"}}  # today's default (a run without one was made on the paper's settings)
    (d / "config.json").write_text(json.dumps(cfg))
    (d / "summary.json").write_text(json.dumps({"unit": unit, "behaviour_normalized_d4rl": behaviour, **(timing or {})}))
    return d


def test_table_column_leaves_out_the_ablations_an_algorithm_is_made_of():
    """MOPO's config turns off the CVAE and the P-MDP's termination itself (configs/algo/mopo.yaml): its runs are the MOPO
    column, not an ablation of it; another algorithm's same switches, or MOPO with one of its own turned back on, say so."""
    from torchrl_offhrl.recipes.report import table_column

    def run(name, **ablation):
        return {"config": {"algo": {"name": name}, "env": {"env_id": "Hopper-v5"}, "dataset": "medium", "ablation": ablation,
                           "model_env": {"latent_origin": "best"}}}

    assert table_column(run("mopo", no_cvae=True, no_pessimism=True)) == "mopo"
    assert table_column(run("mopo", no_cvae=True, no_pessimism=False)) == "mopo [no_pessimism=false]"
    assert table_column(run("sac", no_cvae=True, no_pessimism=True)) == "sac [no_cvae,no_pessimism]"
    assert table_column(run("moc")) == "moc" and table_column(run("moc", no_cvae=True)) == "moc [no_cvae]"
    assert table_column(run("my_own_algo", no_cvae=True)) == "my_own_algo [no_cvae]"  # no shipped config: nothing is its own


def test_paper_table_layout(tmp_path):
    """Rows env x dataset, the paper's columns in order (missing ones as —), final and best apart, published scores apart."""
    from torchrl_offhrl.recipes.report import paper_table

    runs = [
        _fake_run(tmp_path, "moc", 0, "Hopper-v5", "medium", "frames", (10.0, 50.0, 40.0), behaviour=37.0),
        _fake_run(tmp_path, "moc", 1, "Hopper-v5", "medium", "frames", (10.0, 30.0, 60.0), behaviour=37.0),
        _fake_run(tmp_path, "iql", 0, "Hopper-v5", "medium", "updates", (1.0, 45.0, 42.0), behaviour=37.0),
        _fake_run(tmp_path, "morel", 0, "Hopper-v5", "medium", "frames", (5.0, 20.0, 25.0), behaviour=37.0, ablation={"no_cvae": True}),
        _fake_run(tmp_path, "moc", 0, "HalfCheetah-v5", "medium", "frames", (30.0, 40.0, 41.0), behaviour=38.0),
        _fake_run(tmp_path, "ppo", 0, "Hopper-v5", "medium", "frames", (8.0, 9.0, 7.0), behaviour=37.0, ablation={"no_cvae": True}),
    ]
    text = paper_table(runs, tmp_path / "t")
    final = text.split("## Final evaluation")[1].split("## Best")[0]
    best = text.split("## Best")[1].split("## Published")[0]
    # the headline table: the shipped algorithms only
    header = "| dataset | MOC | PPO | SAC | MOReL | MOPO | IQL | CQL | TD3+BC | BC | behaviour data |"
    assert header in final and header in best
    # MOC hopper: finals 40, 60 -> IQM 50.0, bootstrap CI [40, 60]; best after step 0: 50, 60 -> 55.0 [50, 60]
    assert "| hopper-medium | 50.0 [40.0, 60.0] (2) | — | — | — | — | 42.0 (1) | — | — | — | 37.0 |" in final
    assert "| hopper-medium | 55.0 [50.0, 60.0] (2) | — | — | — | — | 45.0 (1) | — | — | — | 37.0 |" in best
    # a MOReL run without the behaviour-cloned start (the config before it followed MOReL's code) and an ablation have columns
    # of their own, on variants.md, in the same layout; the headline page links it
    assert "[variants.md](variants.md)" in text and "MOReL-style" not in text and "no_cvae" not in text
    variants = (tmp_path / "t" / "variants.md").read_text()
    vfinal = variants.split("## Final evaluation")[1].split("## Best")[0]
    assert "| dataset | MOReL-style (old) | ppo [no_cvae] | behaviour data |" in vfinal
    assert "| hopper-medium | 25.0 (1) | 7.0 (1) | 37.0 |" in vfinal and "| halfcheetah-medium | — | — | 38.0 |" in vfinal
    assert "- hopper-medium, ppo [no_cvae]: s0: 7.0 / n/a / " in variants and "- hopper-medium, MOC:" not in variants
    # per seed: final / selected / last-5 mean / best / untrained; MOC's change over its start: +30 and +50
    assert "- hopper-medium, MOC: s0: 40.0 / n/a / 45.0 / 50.0 / 10.0; s1: 60.0 / n/a / 45.0 / 60.0 / 10.0; change over untrained +40.0" in text
    assert (tmp_path / "t" / "performance_profile.png").is_file()
    assert "| halfcheetah-medium | 41.0 (1) | — |" in final
    published = text.split("## Published")[1]
    assert "not ours" in published.split("\n")[0] and "| Offline MOC (the paper) | 76.8 | 107.4 | 45.04 | 90.6 |" in published
    assert "IQL: 200 updates" in text and "MOC: 200 frames" in text
    rows = (tmp_path / "t" / "table.csv").read_text().splitlines()
    assert len(rows) == 1 + 5 and rows[0].startswith("env,dataset,algo,seeds,budget")
    assert (tmp_path / "t" / "curves_hopper-medium.png").is_file() and (tmp_path / "t" / "curves_halfcheetah-medium.png").is_file()
    # every standard column with fewer than min_seeds seeds is listed with its reason: per cell, else per row, else none given
    text = paper_table(runs, tmp_path / "m", min_seeds=2, missing_reasons={"hopper-medium:cql": "CQL needs a GPU.", "hopper-medium": "Not run yet."})
    missing = text.split("## Missing cells (fewer than 2 seeds)")[1].split("## Published")[0]
    assert "- hopper-medium: CQL (no run). CQL needs a GPU." in missing
    assert ("- hopper-medium: PPO (no run), SAC (no run), MOReL (no run), MOPO (no run), IQL (1 seed), TD3+BC (no run), BC (no run). "
            "Not run yet.") in missing
    cheetah = next(line for line in missing.splitlines() if line.startswith("- halfcheetah-medium:"))
    assert cheetah.startswith("- halfcheetah-medium: MOC (1 seed), PPO (no run)") and cheetah.endswith("BC (no run). No reason given.")
    assert "MOC (2" not in missing  # hopper's MOC has its 2 seeds
    every = [_fake_run(tmp_path / "all", a, 0, "Hopper-v5", "medium", "frames", (1.0, 2.0, 3.0), algo_cfg={"bc_init_steps": 10} if a == "morel" else None,
                       ablation={"no_cvae": True, "no_pessimism": True} if a == "mopo" else None)  # as configs/algo/mopo.yaml sets it
             for a in ("moc", "ppo", "sac", "morel", "mopo", "iql", "cql", "td3bc", "bc")]
    assert "None: every column has its seeds." in paper_table(every, tmp_path / "n", min_seeds=1).split("## Missing")[1]
    assert not (tmp_path / "n" / "variants.md").exists()  # nothing but the shipped algorithms: no variants page
    (tmp_path / "t" / "stale").mkdir()
    paper_table(every, tmp_path / "t")  # a report over runs without variants removes an earlier report's page
    assert not (tmp_path / "t" / "variants.md").exists()


def test_paper_table_says_which_dataset_instance_each_run_used(tmp_path):
    """Runs of one row on two generated instances of its dataset (data_hash): the page lists them per instance and marks
    the cell that pools seeds from both; a row on one instance is not listed."""
    from torchrl_offhrl.recipes.report import paper_table

    runs = [
        _fake_run(tmp_path, "moc", 4, "Hopper-v5", "medium-expert", "frames", (10.0, 50.0, 40.0), data_hash="aaaa"),
        _fake_run(tmp_path, "moc", 5, "Hopper-v5", "medium-expert", "frames", (10.0, 30.0, 60.0), data_hash="aaaa"),
        _fake_run(tmp_path, "bc", 4, "Hopper-v5", "medium-expert", "updates", (1.0, 45.0, 42.0), data_hash="bbbb"),
        _fake_run(tmp_path, "bc", 5, "Hopper-v5", "medium-expert", "updates", (1.0, 45.0, 44.0), data_hash="aaaa"),
        _fake_run(tmp_path, "moc", 4, "Hopper-v5", "medium", "frames", (10.0, 20.0, 30.0), data_hash="cccc"),
        _fake_run(tmp_path, "bc", 4, "Hopper-v5", "medium", "updates", (1.0, 25.0, 28.0), data_hash="cccc"),
    ]
    text = paper_table(runs, tmp_path / "t")
    section = text.split("## Dataset instances")[1].split("## Published")[0]
    assert "- hopper-medium-expert: `aaaa`: MOC s4 s5, BC s5; `bbbb`: BC s4" in section
    assert "hopper-medium:" not in section  # one instance
    final = text.split("## Final evaluation")[1].split("## Best")[0]
    me = next(line for line in final.splitlines() if line.startswith("| hopper-medium-expert |"))
    assert "(2) ‡" in me and me.count("‡") == 1  # BC pools the two instances; MOC's seeds share one
    assert "‡" not in next(line for line in final.splitlines() if line.startswith("| hopper-medium |"))
    assert "## Dataset instances" not in paper_table(runs[4:], tmp_path / "u")
    # a variant's runs on another instance: listed (and marked) on variants.md, the page its column is on, not on table.md
    variant = [_fake_run(tmp_path / "v", "moc_fit60k", s, "Hopper-v5", "medium", "frames", (10.0, 20.0, 30.0), data_hash=h)
               for s, h in ((4, "cccc"), (5, "dddd"))]
    text = paper_table([*runs[4:], *variant], tmp_path / "w")
    assert "## Dataset instances" not in text
    variants = (tmp_path / "w" / "variants.md").read_text()
    assert "- hopper-medium: `cccc`: moc_fit60k s4; `dddd`: moc_fit60k s5" in variants.split("## Dataset instances")[1]
    assert "(2) ‡" in next(line for line in variants.splitlines() if line.startswith("| hopper-medium |"))


def test_paper_table_marks_cells_pooling_different_evaluation_episodes(tmp_path):
    """Seeds of one cell evaluated on 10 and on 30 episodes: the cell carries § in every table and the section lists each
    count's seeds; a cell whose seeds share a count, and a page where all do, carry neither."""
    from torchrl_offhrl.recipes.report import paper_table

    runs = []
    for algo, seed, episodes in (("iql", 4, 30), ("iql", 5, 10), ("iql", 6, 10), ("moc", 4, 30), ("moc", 5, 30)):
        d = _fake_run(tmp_path, algo, seed, "Hopper-v5", "medium", "frames" if algo == "moc" else "updates", (1.0, 40.0, 42.0))
        cfg = json.loads((d / "config.json").read_text())
        (d / "config.json").write_text(json.dumps({**cfg, "eval": {"episodes": episodes}}))
        runs.append(d)
    text = paper_table(runs, tmp_path / "t", min_seeds=1)
    section = text.split("## Evaluation episodes")[1].split("## Published")[0]
    assert "- hopper-medium, IQL: 10 episodes: s5 s6; 30 episodes: s4" in section
    assert "MOC" not in section
    for name in ("## Final evaluation", "## Best evaluation"):
        row = next(x for x in text.split(name)[1].splitlines() if x.startswith("| hopper-medium |"))
        assert row.count("§") == 1 and "(3) §" in row  # IQL's three seeds; MOC's two share 30 episodes
    assert "§" not in paper_table([r for r in runs if r.name.startswith("moc")], tmp_path / "u", min_seeds=1)


def test_paper_table_reports_the_sampled_policy_apart_where_runs_evaluated_it(tmp_path):
    """Runs with ``eval.sampled``: a table of the sampled policy's final scores and a sampled value per seed; pages without it keep their layout."""
    from torchrl_offhrl.recipes.report import paper_table

    runs = []
    for seed, final, sampled in ((4, 80.0, 30.0), (5, 40.0, 34.0)):
        d = _fake_run(tmp_path, "moc", seed, "Hopper-v5", "medium", "frames", (20.0, 50.0, final), behaviour=36.0)
        evals = json.loads((d / "evals.json").read_text())
        for e, s in zip(evals, (29.0, 31.0, sampled)):
            e["normalized_d4rl_sampled"] = s
        (d / "evals.json").write_text(json.dumps(evals))
        runs.append(d)
    text = paper_table(runs, tmp_path / "t")
    table = text.split("## Final evaluation of the sampled policy")[1].split("## Best")[0]
    assert "| hopper-medium | 32.0 [30.0, 34.0] (2) |" in table  # the last evaluation's sampled scores, 30 and 34
    assert "| hopper-medium | 60.0 [40.0, 80.0] (2) |" in text.split("## Final evaluation")[1]  # the deterministic ones unchanged
    assert "(final / selected / last-5 mean / best / untrained / final sampled)" in text
    assert "s4: 80.0 / n/a / 65.0 / 80.0 / 20.0 / 30.0; s5: 40.0 / n/a / 45.0 / 50.0 / 20.0 / 34.0" in text
    plain = paper_table([_fake_run(tmp_path / "p", "moc", 4, "Hopper-v5", "medium", "frames", (20.0, 50.0, 80.0))], tmp_path / "q")
    assert "sampled" not in plain and "(final / selected / last-5 mean / best / untrained)" in plain


def test_one_option_moc_runs_get_their_own_column(tmp_path):
    """configs/algo/moc_1opt.yaml (MOC with one option, the options ablation) is labelled apart: never averaged with MOC's two options."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.report import paper_table

    algo = compose("demo", ["algo=moc_1opt"]).algo
    assert algo.name == "moc" and algo.num_options == 1 and algo.label == "moc_1opt"
    runs = [_fake_run(tmp_path, "moc", 4, "Hopper-v5", "medium", "frames", (20.0, 50.0, 80.0), behaviour=36.0),
            _fake_run(tmp_path / "one", "moc", 4, "Hopper-v5", "medium", "frames", (20.0, 30.0, 40.0), behaviour=36.0,
                      algo_cfg={"label": "moc_1opt", "num_options": 1})]
    final = paper_table(runs, tmp_path / "t").split("## Final evaluation")[1].split("## Best")[0]
    assert "| hopper-medium | 80.0 (1) | — | — | — | — | — | — | — | — | 36.0 |" in final  # MOC's own column, 2 options only
    variants = (tmp_path / "t" / "variants.md").read_text().split("## Final evaluation")[1].split("## Best")[0]
    assert "| dataset | MOC, 1 option | behaviour data |" in variants and "| hopper-medium | 40.0 (1) | 36.0 |" in variants


def test_ppoc_is_moc_with_eta_zero_in_a_column_of_its_own(tmp_path):
    """configs/algo/ppoc.yaml (MOC's multi-updates off: eta 0, the second options ablation) is MOC with only eta changed, labelled apart."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.report import paper_table
    from torchrl_offhrl.utils import to_plain

    moc, ppoc = to_plain(compose("demo", ["algo=moc"]).algo), to_plain(compose("demo", ["algo=ppoc"]).algo)
    assert ppoc["name"] == "moc" and ppoc["eta"] == 0.0 and moc["eta"] == 0.7
    assert {k for k in moc.keys() | ppoc.keys() if moc.get(k) != ppoc.get(k)} == {"eta", "label"}
    runs = [_fake_run(tmp_path, "moc", 4, "Hopper-v5", "medium", "frames", (20.0, 50.0, 80.0), behaviour=36.0),
            _fake_run(tmp_path / "ppoc", "moc", 4, "Hopper-v5", "medium", "frames", (20.0, 30.0, 45.0), behaviour=36.0,
                      algo_cfg={"label": "ppoc", "eta": 0.0})]
    final = paper_table(runs, tmp_path / "t").split("## Final evaluation")[1].split("## Best")[0]
    assert "| hopper-medium | 80.0 (1) | — | — | — | — | — | — | — | — | 36.0 |" in final
    variants = (tmp_path / "t" / "variants.md").read_text().split("## Final evaluation")[1].split("## Best")[0]
    assert "| dataset | PPOC (eta 0) | behaviour data |" in variants and "| hopper-medium | 45.0 (1) | 36.0 |" in variants


def test_missing_cells_say_what_a_seed_cost_on_the_page_s_runs(tmp_path):
    """A missing cell's line gives the measured cost of one more seed: the median over that column's timed runs (any row) of
    their total time less the data and the model fits, with the device and threads they ran on."""
    from torchrl_offhrl.recipes.report import paper_table

    runs = [_fake_run(tmp_path, "cql", s, "Hopper-v5", "medium", "updates", (1.0, 2.0, 3.0), behaviour=36.0,
                      timing={"total_s": t, "models_s": 0.0, "data_s": 0.0}) for s, t in ((4, 7200.0), (5, 10800.0), (6, 36000.0))]
    runs.append(_fake_run(tmp_path, "cql", 4, "Hopper-v5", "medium-expert", "updates", (1.0, 2.0, 3.0), behaviour=53.0,
                          timing={"total_s": 5000.0, "models_s": 1400.0, "data_s": 0.0}))
    text = paper_table(runs, tmp_path / "t", min_seeds=3, missing_reasons={"hopper-medium-expert:cql": "Needs a GPU."})
    missing = text.split("## Missing cells")[1].split("## Published")[0]
    line = next(x for x in missing.splitlines() if x.startswith("- hopper-medium-expert: CQL"))
    # timed runs: 7200, 10800, 36000 and 5000 - 1400 = 3600 s -> median (7200 + 10800) / 2 = 9000 s = 2.5 h
    assert line == ("- hopper-medium-expert: CQL (1 seed). Needs a GPU. Measured on this page's runs: CQL 2.5 h per seed "
                    "(cpu, default threads; median of 4 timed runs).")
    assert not any(x.startswith("- hopper-medium: CQL") for x in missing.splitlines())  # 3 seeds: not missing


def test_archived_run_reads_like_its_run_directory(tmp_path):
    """archive_run keeps config, evals and summary byte for byte plus the training scalars' tails; the tables read it the same."""
    from torchrl_offhrl.recipes.report import archive_run, group_stats, load_run

    run = _fake_run(tmp_path / "outputs", "iql", 0, "Hopper-v5", "medium", "updates", (1.0, 45.0, 42.0), behaviour=37.0)
    logs = run / "logs" / "scalars" / "train"
    logs.mkdir(parents=True)
    (logs / "loss_actor.csv").write_text("".join(f"{i},{v}\n" for i, v in enumerate([9.0, 1.0, 2.0, 3.0, 4.0, 5.0])))
    kept = archive_run(run, tmp_path / "docs" / run.name)
    for name in ("config.json", "evals.json", "summary.json"):
        assert (kept / name).read_bytes() == (run / name).read_bytes()
    assert json.loads((kept / "diagnostics.json").read_text()) == {"train_tail_means": {"loss_actor": 3.0}}  # mean of the last 5
    assert sorted(p.name for p in kept.iterdir()) == ["config.json", "diagnostics.json", "evals.json", "summary.json"]  # no temporary files left
    assert group_stats([load_run(kept)]) == group_stats([load_run(run)])
    (run / "summary.json").unlink()
    with pytest.raises(FileNotFoundError, match="has not finished"):
        archive_run(run, tmp_path / "docs" / "again")


def test_archive_overwrites_only_the_same_run(tmp_path):
    """Archiving again after a resume (more evaluations, same config) updates the archive; another run of the same name (here
    another algorithm config) raises and leaves the old archive byte for byte as it was."""
    from torchrl_offhrl.recipes.report import archive_run

    run = _fake_run(tmp_path / "a", "morel", 4, "Hopper-v5", "medium", "frames", (1.0, 30.0), behaviour=37.0)
    kept = archive_run(run, tmp_path / "docs" / "morel-hopper-medium-seed4")
    resumed = _fake_run(tmp_path / "b", "morel", 4, "Hopper-v5", "medium", "frames", (1.0, 30.0, 50.0), behaviour=37.0)
    cfg = json.loads((resumed / "config.json").read_text())
    cfg["eval"] = {**(cfg.get("eval") or {}), "episodes": 30}  # an evaluation setting: still the same run
    (resumed / "config.json").write_text(json.dumps(cfg))
    archive_run(resumed, kept)
    assert (kept / "evals.json").read_bytes() == (resumed / "evals.json").read_bytes()
    other = _fake_run(tmp_path / "c", "morel", 4, "Hopper-v5", "medium", "frames", (2.0, 60.0), behaviour=37.0)
    cfg = json.loads((other / "config.json").read_text())
    cfg["algo"] = {**cfg["algo"], "bc_init_steps": 1000}  # MOReL from a behaviour-cloned start: another run
    (other / "config.json").write_text(json.dumps(cfg))
    before = {p.name: p.read_bytes() for p in kept.iterdir()}
    with pytest.raises(FileExistsError, match="archives another run"):
        archive_run(other, kept)
    assert {p.name: p.read_bytes() for p in kept.iterdir()} == before


def test_partial_runs_count_in_the_tables_but_draw_no_curves(tmp_path):
    """A run known by a few evaluations only (a dict with partial=True) enters the mean +- std; the curves show the whole runs only."""
    from torchrl_offhrl.recipes.report import aggregate, load_run, paper_table

    whole = load_run(_fake_run(tmp_path, "moc", 0, "Hopper-v5", "medium", "frames", (10.0, 50.0, 40.0), behaviour=37.0))
    part = {**whole, "dir": "legacy#moc-seed1", "partial": True, "evals": [{"step": 0, "frames": 0, "normalized_d4rl": 10.0, "return_mean": 100.0},
                                                                            {"step": 200, "frames": 200, "normalized_d4rl": 60.0, "return_mean": 600.0}]}
    text = paper_table([whole, part], tmp_path / "t")
    assert "| hopper-medium | 50.0 [40.0, 60.0] (2) |" in text.split("## Best")[0]  # finals 40 and 60
    assert "| hopper-medium | 55.0 [50.0, 60.0] (2) |" in text.split("## Best")[1]  # best after step 0: 50 and 60
    assert "s0*: 60.0 / n/a / n/a / 60.0 / 10.0" in text  # the partial run (its config is seed 0's): marked, no last five
    assert "`*`: a run known only from an earlier page" in text
    assert "`*`:" not in paper_table([whole], tmp_path / "w")  # no marked row, no legend
    assert (tmp_path / "t" / "curves_hopper-medium.png").is_file()
    only_partial = paper_table([part], tmp_path / "p")
    assert "| hopper-medium | 60.0 (1) |" in only_partial and not list((tmp_path / "p").glob("curves*.png"))
    aggregate([part], tmp_path / "a")
    assert (tmp_path / "a" / "results.csv").is_file() and not (tmp_path / "a" / "curves.png").exists()


def test_results_script_rebuilds_lost_runs_from_the_committed_record():
    """experiments/results/table1.py: the committed legacy record gives back the committed table's per-seed scores, and a rerun takes a run's place."""
    mod = import_module("experiments.results.table1")
    runs, diag = mod.legacy_runs("full", skip=set())
    by_name = {r["name"]: r for r in runs}
    seed4 = by_name["moc-hopper-medium-seed4"]  # start 31.4, final 95.9, best 95.9 at the end: two evaluations
    assert [e["step"] for e in seed4["evals"]] == [0, 204800] and seed4["evals"][-1]["normalized_d4rl"] == 95.9
    seed5 = by_name["moc-hopper-medium-seed5"]  # final 83.8, best 88.1 at 163840 frames
    assert [(e["step"], e["normalized_d4rl"]) for e in seed5["evals"]] == [(0, 30.5), (163840, 88.1), (204800, 83.8)]
    from torchrl_offhrl.scores import normalized_score
    assert normalized_score("Hopper-v5", seed5["evals"][-1]["return_mean"]) == pytest.approx(83.8)
    assert by_name["morel-hopper-medium-seed4"]["config"]["algo"]["label"] == "morel" and all(r["partial"] for r in runs)
    assert set(diag) == {"moc-hopper", "moc-halfcheetah"}
    assert "moc-hopper-medium-seed4" not in {r["name"] for r in mod.legacy_runs("full", skip={"moc-hopper-medium-seed4"})[0]}


def test_results_script_runs_the_medium_expert_rows_in_their_own_run_directories(monkeypatch):
    """experiments/results/table1.py run --datasets medium-expert: the dataset reaches the config and names the run directory."""
    import torchrl_offhrl.recipes.train as train_mod

    mod = import_module("experiments.results.table1")
    seen = []
    monkeypatch.setattr(train_mod, "train", lambda cfg: seen.append(cfg) or {"final": {"normalized_d4rl": 1.0}})
    monkeypatch.setattr(mod, "archive", lambda scale: [])
    mod.main(["run", "--scale", "full", "--envs", "hopper", "--algos", "bc", "--seeds", "4", "--datasets", "medium", "medium-expert"])
    assert [c["dataset"] for c in seen] == ["medium", "medium-expert"]
    assert [Path(c["run_dir"]).name for c in seen] == ["bc-hopper-medium-seed4", "bc-hopper-medium-expert-seed4"]
    assert all(c["train"]["total_updates"] == 100000 for c in seen)
    # --speed: settings that change how fast a run goes reach it; one that would change the run itself is refused
    mod.main(["run", "--scale", "full", "--envs", "hopper", "--algos", "cql", "--seeds", "4", "--speed", "device=cuda", "algo.cudagraphs=true"])
    assert seen[-1]["device"] == "cuda" and seen[-1]["algo"]["cudagraphs"] is True and Path(seen[-1]["run_dir"]).name == "cql-hopper-medium-seed4"
    with pytest.raises(SystemExit, match="change the run itself"):
        mod.main(["run", "--scale", "full", "--envs", "hopper", "--algos", "cql", "--seeds", "4", "--speed", "algo.num_random=2"])


def test_results_script_keeps_tuning_runs_apart(monkeypatch):
    """experiments/results/table1.py run --tuning: seeds 1-3 by default, run directories and archive under <scale>_tuning; seeds 4-6 refused."""
    import torchrl_offhrl.recipes.train as train_mod

    mod = import_module("experiments.results.table1")
    seen, archived = [], []
    monkeypatch.setattr(train_mod, "train", lambda cfg: seen.append(cfg) or {"final": {"normalized_d4rl": 1.0}})
    monkeypatch.setattr(mod, "archive", lambda scale: archived.append(scale) or [])
    mod.main(["run", "--tuning", "--envs", "hopper", "--algos", "moc_online"])
    assert [c["seed"] for c in seen] == [1, 2, 3] and set(archived) == {"demo_tuning"}
    assert [Path(c["run_dir"]).parent.name for c in seen] == ["demo_tuning"] * 3
    assert seen[0]["algo"]["label"] == "moc_online"
    mod.main(["run", "--envs", "hopper", "--algos", "moc", "--seeds", "4"])
    assert Path(seen[-1]["run_dir"]).parent.name == "demo" and archived[-1] == "demo"
    with pytest.raises(SystemExit, match="evaluation seeds"):
        mod.main(["run", "--tuning", "--seeds", "3", "4"])
    # --extra ... --tag T: a variant of the scale's config, in run directories and a column (algo.label) of its own
    mod.main(["run", "--tuning", "--scale", "full", "--envs", "hopper", "--algos", "moc", "--seeds", "2",
              "--extra", "model_env.reset_states=any", "model_env.horizon=100", "--tag", "branch"])
    assert Path(seen[-1]["run_dir"]).name == "moc_branch-hopper-medium-seed2" and seen[-1]["algo"]["label"] == "moc_branch"
    assert seen[-1]["model_env"]["horizon"] == 100 and seen[-1]["model_env"]["reset_states"] == "any"
    assert seen[-1]["algo"]["minibatch_size"] == 256 and seen[-1]["train"]["total_frames"] == 204800  # the scale's own settings stay
    mod.main(["run", "--tuning", "--scale", "full", "--envs", "hopper", "--algos", "moc", "--seeds", "2"])  # the default: the rules
    assert seen[-1]["model_env"]["horizon"] == "auto" and seen[-1]["model_env"]["latent_origin"] == "best"
    assert "label" not in seen[-1]["algo"] and Path(seen[-1]["run_dir"]).name == "moc-hopper-medium-seed2"
    mod.main(["run", "--tuning", "--scale", "full", "--envs", "hopper", "--algos", "moc", "--seeds", "2", "--paper"])
    assert seen[-1]["model_env"]["horizon"] == 1000 and seen[-1]["model_env"]["latent_origin"] == "zero"
    assert Path(seen[-1]["run_dir"]).name == "moc_paper-hopper-medium-seed2"  # beside the default's, never over it
    with pytest.raises(SystemExit, match="go together"):
        mod.main(["run", "--tuning", "--algos", "moc", "--extra", "model_env.horizon=100"])


def test_transfer_script_keeps_variants_and_tuning_runs_apart(monkeypatch):
    """experiments/results/transfer.py run --tuning --tag T --extra ...: the overrides reach the config, the tag names the run
    directory and the rows (algo.label), tuning runs go to their own folder; seeds 4-6 and untagged overrides are refused."""
    import torchrl_offhrl.recipes.train as train_mod

    mod = import_module("experiments.results.transfer")
    seen = []
    monkeypatch.setattr(train_mod, "train", lambda cfg: seen.append(cfg) or {"run_dir": cfg["run_dir"], "algo": "moc"})
    monkeypatch.setattr("torchrl_offhrl.recipes.report.format_summary", lambda s: "")
    monkeypatch.setattr(mod, "archive", lambda tuning=False: [])
    mod.main(["run", "--tuning", "--envs", "halfcheetah", "--algos", "moc", "--kinds", "scratch", "--tag", "constlr", "--extra", "algo.anneal_lr=false"])
    mod.main(["run", "--envs", "hopper", "--algos", "ppo", "--kinds", "transfer", "--seeds", "5"])
    (tuned, plain) = seen
    assert Path(tuned["run_dir"]) == mod.TUNING_OUT / "moc-halfcheetah-medium-scratch-constlr-seed1" and tuned["seed"] == 1
    assert tuned["algo"]["anneal_lr"] is False and tuned["algo"]["label"] == "moc_constlr" and tuned["transfer"]["from_scratch"] is True
    assert Path(plain["run_dir"]) == mod.OUT / "ppo-hopper-medium-transfer-seed5" and "label" not in plain["algo"]
    with pytest.raises(SystemExit, match="evaluation seeds"):
        mod.main(["run", "--tuning", "--seeds", "1", "4"])
    with pytest.raises(SystemExit, match="--tag"):
        mod.main(["run", "--extra", "algo.lr=1e-3"])


def test_morel_is_one_named_config():
    """algo=morel: MOReL as its official code runs D4RL Hopper: a behaviour-cloned start, a KL-bounded policy step (PPO's
    adaptive KL penalty at NPG's ~0.01 per iteration), 700-step episodes from the data's start states at discount 0.999,
    the max-pairwise discrepancy and its threshold rule (3.0 x the data's max, HALT reward 0), in real actions."""
    cfg = to_plain(compose("offline_train", ["algo=morel", "env=hopper", "dataset=medium"]))
    assert cfg["algo"]["name"] == "ppo" and cfg["algo"]["label"] == "morel"
    assert cfg["ablation"]["no_cvae"] is True and cfg["model_env"]["discrepancy"] == "max_pairwise"
    assert cfg["model_env"]["pessimism"] == {"fraction": 3.0, "penalty": 0.0}
    assert (cfg["model_env"]["horizon"], cfg["model_env"]["reset_states"]) == (700, "initial")
    assert (cfg["algo"]["loss_type"], cfg["algo"]["dtarg"], cfg["algo"]["gamma"], cfg["algo"]["lmbda"]) == ("kl", 0.01, 0.999, 0.97)
    assert cfg["algo"]["bc_init_steps"] > 0
    # the command line still wins over the named config, and the other algorithms keep the defaults
    assert to_plain(compose("offline_train", ["algo=morel", "model_env.discrepancy=variance"]))["model_env"]["discrepancy"] == "variance"
    plain = to_plain(compose("offline_train", ["algo=ppo"]))
    assert plain["ablation"]["no_cvae"] is False and plain["model_env"]["discrepancy"] == "variance"


def test_morel_trains_end_to_end(hopper_file, cache, tmp_path):
    tiny = ["ensemble.hidden_sizes=[16]", "ensemble.fit.max_steps=20", "cvae.hidden_sizes=[16]", "cvae.fit.max_steps=20", "collector.num_envs=4",
            "train.total_frames=64", "eval.every_frames=64", "algo.frames_per_batch=64", "algo.epochs=1", "eval.episodes=2", "eval.max_steps=15",
            "algo.bc_init_steps=200", "model_env.horizon=15"]
    summary = train(to_plain(compose("offline_train", ["algo=morel", f"dataset={hopper_file}", f"out_root={tmp_path}", *tiny])), progress=False)
    run = Path(summary["run_dir"])
    assert run.name.startswith("morel-hopper-hopper_random-") and run.name.endswith("-no_cvae-seed0")
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["resolved_pessimism"] == {"fraction": 3.0, "penalty": 0.0}  # MOReL's HALT: the episode ends, reward 0
    bc = json.loads((run / "pretrain.json").read_text())  # the behaviour-cloned start was fitted before the first evaluation
    assert bc["bc_init_steps"] == 200 and bc["bc_init_nll_last"] < bc["bc_init_nll_first"]
    from torchrl_offhrl.models import DynamicsEnsemble

    ensemble = DynamicsEnsemble.load(Path(cfg["model_dir"]) / "ensemble.pt")
    from torchrl_offhrl.data import load_dataset
    from torchrl_offhrl.envs import dataset_discrepancy

    d = dataset_discrepancy(ensemble, load_dataset(hopper_file), "max_pairwise")
    assert cfg["threshold"] == pytest.approx(float(d.max()) * 3, rel=1e-4)


def test_offhrl_evaluate_rebuilds_a_dataset_agent(hopper_file, cache, tmp_path):
    """A dataset agent's checkpoint is evaluated like any run's: real actions, no CVAE, its resolved reward scale."""
    from torchrl_offhrl.recipes.evaluation import evaluate_run

    summary = train(_cfg("iql", hopper_file, tmp_path, "train.total_updates=10", "eval.every_updates=10"), progress=False)
    res = evaluate_run(summary["run_dir"], episodes=2, seed=summary["seed"] * 1000 + 7)
    assert res["return_mean"] == pytest.approx(summary["final"]["return_mean"], rel=1e-5)  # the same episodes as the run's evaluation


def test_offhrl_report_on_real_runs(hopper_file, cache, tmp_path, capsys):
    """Runs written by `train` (a dataset agent and a model-env agent) go straight into `offhrl report` and `offhrl aggregate`."""
    from torchrl_offhrl.cli import main

    bc = train(_cfg("bc", hopper_file, tmp_path / "runs", "train.total_updates=4", "eval.every_updates=2"), progress=False)
    tiny = ["ensemble.hidden_sizes=[16]", "ensemble.fit.max_steps=10", "cvae.hidden_sizes=[16]", "cvae.fit.max_steps=10", "collector.num_envs=4",
            "train.total_frames=64", "eval.every_frames=64", "algo.frames_per_batch=64", "algo.epochs=1", "eval.episodes=2", "eval.max_steps=30",
            "eval.model_env=false"]
    ppo = train(to_plain(compose("offline_train", ["algo=ppo", f"dataset={hopper_file}", f"out_root={tmp_path / 'runs'}", *tiny])), progress=False)
    assert main(["report", bc["run_dir"], ppo["run_dir"], "--out", str(tmp_path / "t")]) == 0
    table = (tmp_path / "t" / "table.md").read_text()
    row = next(line for line in table.split("## Best")[0].splitlines() if line.startswith("| hopper-hopper_random"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2].endswith("(1)") and cells[9].endswith("(1)") and cells[1] == "—"  # PPO and BC filled, MOC missing
    assert f"{bc['final']['normalized_d4rl']:.1f} (1)" == cells[9]  # one seed: no spread shown
    assert "BC: 4 updates" in table and "PPO: 64 frames" in table
    assert "- hopper-hopper_random: MOC (no run), PPO (1 seed)" in table  # --min-seeds defaults to 3
    assert main(["report", bc["run_dir"], ppo["run_dir"], "--out", str(tmp_path / "t1"), "--min-seeds", "1"]) == 0
    assert "- hopper-hopper_random: MOC (no run), SAC (no run)" in (tmp_path / "t1" / "table.md").read_text()
    assert main(["aggregate", bc["run_dir"], ppo["run_dir"], "--out", str(tmp_path / "a")]) == 0
    assert "| bc | Hopper-v5 |" in (tmp_path / "a" / "results.md").read_text()


def test_pessimism_overrides_from_the_command_line_and_resume_fingerprint():
    """`model_env.pessimism={...}` overrides the env group's table (it failed while the default was {}); null and {} are the same run."""
    from torchrl_offhrl.recipes.config import config_fingerprint, model_env_config

    cfg = to_plain(compose("offline_train", ["env=hopper", "model_env.pessimism={quantile: 0.95, penalty: 30}"]))
    _, pess = model_env_config({**cfg, "model_env": {**cfg["model_env"], "reward_scale": 1.0}}, "medium")
    assert pess == {"quantile": 0.95, "penalty": 30}  # the quantile replaces the table's fraction 1.08
    plain = to_plain(compose("offline_train", []))
    assert plain["model_env"]["pessimism"] is None
    assert config_fingerprint(plain) == config_fingerprint({**plain, "model_env": {**plain["model_env"], "pessimism": {}}})
    assert config_fingerprint(plain) != config_fingerprint(cfg)


def test_fingerprint_ignores_model_settings_only_for_agents_that_fit_no_model():
    """A dataset agent (td3bc) resumes after a change of the ensemble's fit settings it never uses; a model-env agent (moc) does not."""
    from torchrl_offhrl.recipes.config import config_fingerprint

    for algo, same in (("td3bc", True), ("bc", True), ("moc", False)):
        a = to_plain(compose("offline_train", [f"algo={algo}"]))
        b = to_plain(compose("offline_train", [f"algo={algo}", "ensemble.fit.lr=0.5", "cvae.hidden_sizes=[8]"]))
        assert (config_fingerprint(a) == config_fingerprint(b)) is same, algo
        c = to_plain(compose("offline_train", [f"algo={algo}", "seed=3"]))
        assert config_fingerprint(a) != config_fingerprint(c), algo  # what the agent does use still counts


def test_fingerprint_ignores_the_compile_switch():
    """algo.compile is a speed switch: a run resumes compiled or not, and checkpoints from before the key existed still match."""
    import json

    from torchrl_offhrl.recipes.config import config_fingerprint, fingerprints_match

    for algo in ("iql", "sac", "moc"):
        off = to_plain(compose("offline_train", [f"algo={algo}"]))
        on = to_plain(compose("offline_train", [f"algo={algo}", "algo.compile=true"]))
        assert config_fingerprint(off) == config_fingerprint(on), algo
        older = {k: v for k, v in off.items() if k not in ("train", "eval")}
        older["algo"] = {k: v for k, v in off["algo"].items() if k != "compile"}
        assert fingerprints_match(json.dumps(older, sort_keys=True, default=str), config_fingerprint(on)), algo
        changed = to_plain(compose("offline_train", [f"algo={algo}", "algo.compile=true", "algo.lr=0.1"]))
        assert config_fingerprint(changed) != config_fingerprint(on), algo


def test_fingerprint_of_a_setting_added_later_at_its_old_value():
    """algo.intra_head_gain came after MOC runs existed: at 0.01 (what those runs did) it is the same run, at 1.0 another."""
    import json

    from torchrl_offhrl.recipes.config import config_fingerprint, fingerprints_match

    now = to_plain(compose("offline_train", ["algo=moc"]))
    assert now["algo"]["intra_head_gain"] == 0.01
    older = {k: v for k, v in now.items() if k not in ("train", "eval")}
    older["algo"] = {k: v for k, v in now["algo"].items() if k != "intra_head_gain"}
    assert fingerprints_match(json.dumps(older, sort_keys=True, default=str), config_fingerprint(now))
    wider = to_plain(compose("offline_train", ["algo=moc", "algo.intra_head_gain=1.0"]))
    assert config_fingerprint(wider) != config_fingerprint(now)
    # the same rule for ensemble.reward_hidden_sizes: null (the transition widths) is a run from before the key, a width is not
    assert now["ensemble"]["reward_hidden_sizes"] is None
    no_key = {**now, "ensemble": {k: v for k, v in now["ensemble"].items() if k != "reward_hidden_sizes"}}
    assert config_fingerprint(no_key) == config_fingerprint(now)
    sized = to_plain(compose("offline_train", ["algo=moc", "ensemble.reward_hidden_sizes=[64]"]))
    assert config_fingerprint(sized) != config_fingerprint(now)
    # the loss arguments moc.yaml lists since MOCAgent stopped restating them: at the loss's defaults, a run from before
    no_keys = {**now, "algo": {k: v for k, v in now["algo"].items() if k not in ("termination_coef", "option_coef", "normalize_advantage")}}
    assert config_fingerprint(no_keys) == config_fingerprint(now)
    weighted = to_plain(compose("offline_train", ["algo=moc", "algo.option_coef=0.5"]))
    assert config_fingerprint(weighted) != config_fingerprint(now)


def test_checkpoints_fingerprinted_under_older_rules_still_resume():
    """A td3bc checkpoint whose fingerprint still held the (then different) model settings matches today's run; other changes do not."""
    import json

    from torchrl_offhrl.recipes.config import RESUMABLE_KEYS, config_fingerprint, fingerprints_match

    def legacy(cfg):  # the fingerprint as written before the model settings of dataset agents were dropped from it
        return json.dumps({k: v for k, v in cfg.items() if k not in RESUMABLE_KEYS and k != "transfer"}, sort_keys=True, default=str)

    now = to_plain(compose("offline_train", ["algo=td3bc"]))
    then = to_plain(compose("offline_train", ["algo=td3bc", "ensemble.fit.lr=0.0001"]))
    assert legacy(then) != config_fingerprint(now)
    assert fingerprints_match(legacy(then), config_fingerprint(now))
    assert fingerprints_match(None, config_fingerprint(now))  # checkpoints older than fingerprints
    other_seed = to_plain(compose("offline_train", ["algo=td3bc", "seed=3", "ensemble.fit.lr=0.0001"]))
    assert not fingerprints_match(legacy(other_seed), config_fingerprint(now))
    assert not fingerprints_match("not json", config_fingerprint(now))
    moc_now = to_plain(compose("offline_train", ["algo=moc"]))
    moc_then = to_plain(compose("offline_train", ["algo=moc", "ensemble.fit.lr=0.0001"]))
    assert not fingerprints_match(legacy(moc_then), config_fingerprint(moc_now))  # a model-env agent did use those models


@pytest.mark.parametrize("algo", ["cql", "td3bc"])
def test_cudagraphs_switch_is_the_same_update_off_a_gpu(algo):
    """cudagraphs=true changes nothing on a CPU (no graph is made); a state saved with capturable optimisers loads capturable-free; not in the fingerprint."""
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.recipes.config import compose, config_fingerprint

    agents = pendulum_agents(algo, "cudagraphs", (False, True), {"policy_eval_start": 2} if algo == "cql" else {}, updates=4)
    td = make_gym_env("Pendulum-v1").rollout(8, break_when_any_done=False).reshape(-1)
    (eager, m0), (graphs, m1) = agents
    assert graphs.cudagraphs and all(callable(f) and type(f).__name__ == "function" for f in graphs.__dict__["_step_fns"].values())
    for (name, a), b in zip(eager.loss.state_dict().items(), graphs.loss.state_dict().values()):
        assert torch.equal(a, b), name
    assert [sorted(m) for m in m0] == [sorted(m) for m in m1] and all(torch.is_tensor(v) for m in m1 for k, v in m.items() if k != "updates")
    state = graphs.state_dict()
    assert state["steps"] == 4
    for group in state["optimizer"]["param_groups"]:
        group["capturable"] = True  # as a run captured on a GPU saves them
    graphs.load_state_dict(state)
    assert graphs.steps == 4 and not any(g["capturable"] for o in graphs.optimizers() for g in o.param_groups)
    assert "_step_fns" not in graphs.__dict__
    graphs.update(td)
    base = to_plain(compose("offline_train", [f"algo={algo}", "dataset=hopper-medium"]))
    fast = to_plain(compose("offline_train", [f"algo={algo}", "dataset=hopper-medium", "algo.cudagraphs=true"]))
    assert base["algo"]["cudagraphs"] is False and config_fingerprint(base) == config_fingerprint(fast)


def test_transfer_script_compares_deterministic_and_sampled_final_policies(monkeypatch, tmp_path):
    """experiments/results/transfer.py sampled: each finished run evaluated both ways on the same seed, mean ± std per group, cached until the run moves."""
    import torchrl_offhrl.recipes.evaluation as ev_mod

    mod = import_module("experiments.results.transfer")
    monkeypatch.setattr(mod, "OUT", tmp_path / "runs")
    monkeypatch.setattr(mod, "SAMPLED_PAGE", tmp_path / "sampled.md")
    for seed in (4, 5):
        d = tmp_path / "runs" / f"ppo-hopper-medium-transfer-seed{seed}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text("{}")
        (d / "checkpoint.pt").write_text("")
    (tmp_path / "runs" / "ppo-hopper-medium-scratch-seed4").mkdir()  # unfinished: skipped
    calls = []

    def fake(run_dir, episodes, seed, deterministic):
        calls.append((Path(run_dir).name, seed, deterministic))
        s = int(Path(run_dir).name[-1])
        return {"task": "backward", "return_mean": 1000.0 + 100 * s if deterministic else 900.0 + 10 * s, "return_std": 1.0}

    monkeypatch.setattr(ev_mod, "evaluate_run", fake)
    text = mod.sampled(["hopper"], episodes=3)
    assert len(calls) == 4 and {c[1] for c in calls} == {12345}
    assert "| ppo-hopper-medium-transfer | 2 | 1,450 ± 71 | 945 ± 7 | -505 | 4: 1,400 / 940, 5: 1,500 / 950 |" in text
    mod.sampled(["hopper"], episodes=3)
    assert len(calls) == 4  # cached: the runs have not moved
    mod.sampled(["hopper"], episodes=5)
    assert len(calls) == 8  # another episode count is another measurement


def test_transfer_page_lists_the_rows_short_of_three_seeds():
    """Every row the transfer setting asks for is named on the page while it has fewer than 3 seeds, with its reason."""
    mod = import_module("experiments.results.transfer")
    names = [f"{a}-{e}-medium-{k}-seed{s}" for a, e, k in mod.EXPECTED for s in (4, 5, 6)]
    assert mod.short_rows(names) == []
    names.remove("ppo-hopper-medium-scratch-seed6")
    names = [n for n in names if not n.startswith("sac-halfcheetah-medium-transfer")] + ["moc_online-hopper-medium-scratch-seed4"]
    lines = mod.short_rows(names)
    assert lines[0] == "- ppo on hopper, scratch: 2 of 3 seeds. Running or queued on the CPU."
    assert lines[1].startswith("- sac on halfcheetah, transfer: 0 of 3 seeds. Running or queued on the CPU: SAC makes one gradient step per frame")
    assert len(lines) == 2  # a variant's rows (moc_online) count for none of the expected ones


def test_dataset_agent_probe_rolls_out_what_the_evaluation_scores(hopper_file, cache, tmp_path, capsys):
    """experiments/diagnostics/dataset_agent_probe.py: the same episodes as `offhrl evaluate` (returns equal), one line each, the critic's Q where there is one."""
    mod = load_script("dataset_agent_probe")
    for algo in ("td3bc", "bc"):
        run = train(_cfg(algo, hopper_file, tmp_path / algo, "train.total_updates=4", "eval.every_updates=4"), progress=False)["run_dir"]
        mod.main([run, "--episodes", "3", "--seed", "7", "--data-states", "50"])
        out = capsys.readouterr().out
        expected = evaluation_mod.evaluate_run(run, episodes=3, seed=7)["returns"]
        lines = [line for line in out.splitlines() if line.startswith("  episode ")]
        assert len(lines) == 3
        assert [float(line.split("return")[1].split(",")[0]) for line in lines] == pytest.approx(expected, abs=0.051)
        assert all(("Q(s, pi(s))" in line) == (algo == "td3bc") for line in lines)
        if algo == "td3bc":
            assert json.loads(out.strip().splitlines()[-1])["returns"] == pytest.approx(expected, abs=0.051)
            assert "Q(s, pi(s)) on 50 " in out and " data states: " in out
        else:
            assert "(no critic: BC)" in out and "data states" not in out


def test_moc_settings_added_this_session_keep_older_runs_resumable():
    """algo.loss and algo.policy_ema came after MOC runs existed: at null (what those runs did) a checkpoint written
    without the keys still resumes; a loss or an average set is another run."""
    from torchrl_offhrl.recipes.config import config_fingerprint

    now = to_plain(compose("offline_train", ["algo=moc"]))
    assert now["algo"]["loss"] is None and now["algo"]["policy_ema"] is None
    older = {**now, "algo": {k: v for k, v in now["algo"].items() if k not in ("loss", "policy_ema", "log_std_lr", "final_log_std", "prior_coef")}}
    assert config_fingerprint(older) == config_fingerprint(now)
    for extra in ("algo.policy_ema=0.1", "algo.loss=torchrl_offhrl.objectives.OptionCriticLoss", "algo.log_std_lr=0.01", "algo.final_log_std=-1.0", "algo.prior_coef=1.0"):
        assert config_fingerprint(to_plain(compose("offline_train", ["algo=moc", extra]))) != config_fingerprint(now), extra


def test_pages_name_the_command_that_rebuilds_them(tmp_path, monkeypatch):
    """`offhrl aggregate` / `offhrl report` write the command as typed on the page's first lines (results.md, table.md)."""
    import sys

    from torchrl_offhrl.cli import main

    runs = sorted(str(d) for d in (Path(__file__).parents[1] / "docs" / "results" / "full" / "runs").glob("bc-halfcheetah-medium-seed*"))[:2]
    assert runs
    for cmd, page in (("aggregate", "results.md"), ("report", "table.md")):
        argv = [cmd, *runs, "--out", str(tmp_path / cmd)]
        monkeypatch.setattr(sys, "argv", ["offhrl", *argv])
        assert main(argv) == 0
        text = (tmp_path / cmd / page).read_text()
        assert any(line.startswith(f"Made by `offhrl {cmd} {runs[0]}") for line in text.splitlines()[:3]), text[:300]


def test_ppo_bc_init_clones_the_data_and_the_kl_loss_trains():
    """algo.bc_init_steps: PPO's pretrain fits the actor to the dataset's actions (here a constant 0.5 in every dimension,
    which the cloned policy's deterministic action then reproduces); 0 does nothing; an agent acting in latent actions is
    refused with the fix named. algo.loss_type=kl: TorchRL's KLPENPPOLoss (as BatchableKLPENPPOLoss), whose KL coefficient
    adapts in an update."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env, make_toy_dataset

    env = make_gym_env("Pendulum-v1", num_envs=4)
    d = make_toy_dataset(num_episodes=8, episode_length=25, obs_dim=3, action_dim=1)
    d.data["action"] = torch.full_like(d.data["action"], 0.5)
    torch.manual_seed(0)
    agent = make_agent("ppo", env, action_key="action", hidden_sizes=[16], bc_init_steps=300, bc_init_lr=3e-3, loss_type="kl")
    agent.attach(env)
    out = agent.pretrain(d, progress=True)  # with its progress bar (on stderr): the steps are the same
    assert out["bc_init_steps"] == 300 and out["bc_init_nll_last"] < out["bc_init_nll_first"]
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        act = agent.policy(d[:64].select("observation").clone())["action"]
    low, high = float(env.action_spec.space.low.flatten()[0]), float(env.action_spec.space.high.flatten()[0])  # Pendulum: [-2, 2]
    assert (low, high) == (-2.0, 2.0)
    assert torch.allclose(act, torch.full_like(act, 0.5), atol=0.1)
    assert make_agent("ppo", env, action_key="action", hidden_sizes=[16]).pretrain(d) == {}
    with pytest.raises(ValueError, match="ablation.no_cvae=true"):
        make_agent("ppo", env, action_key="action", hidden_sizes=[16], bc_init_steps=5).pretrain(d.data.exclude("action"))
    beta = float(agent.loss.beta)
    env.set_seed(0)  # the start states too: unseeded, the update's KL can land in the band where beta stays (seen once, 2026-12-03)
    with torch.no_grad():
        batch = env.rollout(64, agent.policy, break_when_any_done=False)
    agent.update(batch)
    assert type(agent.loss).__name__ == "BatchableKLPENPPOLoss" and float(agent.loss.beta) != beta
    with pytest.raises(ValueError, match="loss_type must be 'clip'"):
        make_agent("ppo", env, action_key="action", loss_type="trpo")
