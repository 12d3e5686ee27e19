"""CUDA: every flat agent trains end to end with ``device=cuda``, and the run resumes on the CPU (skipped without CUDA).

The other CUDA tests sit next to what they check (test_data.py, test_envs.py,
test_behaviour.py); this file runs the whole training pipeline: data, model
fit, model env, collector or dataset batches, updates, evaluation, checkpoint.
"""
import json
from pathlib import Path

import pytest
import torch

from torchrl_offhrl.recipes.config import compose
from torchrl_offhrl.recipes.train import train
from torchrl_offhrl.utils import to_plain

from test_offline_agents import DATASET_ALGOS, MODEL_EXTRA, TINY_MODEL, pendulum_agents

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

MODEL_ALGOS = ["moc", "ppo", "sac", "morel"]
EXTRA = {**MODEL_EXTRA, "morel": ["algo.epochs=1"]}


def _cfg(algo, data, out, device, budget):
    if algo in DATASET_ALGOS:
        over = [f"train.total_updates={budget}", "eval.every_updates=10", "algo.batch_size=16"]
    else:
        over = [*TINY_MODEL, f"train.total_frames={budget * 64}", "eval.every_frames=64", *EXTRA.get(algo, [])]
    return to_plain(compose("offline_train", [f"algo={algo}", f"dataset={data}", f"out_root={out}", f"device={device}",
                                              "eval.episodes=2", "eval.max_steps=20", "algo.hidden_sizes=[16,16]",
                                              *over]))


@pytest.mark.parametrize("algo", DATASET_ALGOS + MODEL_ALGOS)
def test_agent_trains_on_cuda_and_resumes_on_the_cpu(algo, hopper_file, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    first = train(_cfg(algo, hopper_file, tmp_path, "cuda", 10 if algo in DATASET_ALGOS else 1), progress=False)
    run = Path(first["run_dir"])
    if algo in ("moc", "ppo"):  # the guard's percentile BC, fitted and evaluated on the GPU beside the agent (recipes.fallback)
        assert first["guard"]["against"] in ("start", "bc") and torch.isfinite(torch.tensor(first["fallback"]["return_mean"]))
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=True)
    params = [v for v in state["agent"]["loss"].values() if v.is_floating_point()]
    assert params and all(torch.isfinite(v).all() for v in params)
    second = train(_cfg(algo, hopper_file, tmp_path, "cpu", 20 if algo in DATASET_ALGOS else 2), progress=False)
    assert second["run_dir"] == first["run_dir"] and second["step"] == 2 * first["step"] > 0
    evals = json.loads((run / "evals.json").read_text())
    assert [e["step"] for e in evals][-2:] == [first["step"], second["step"]]
    assert all(torch.isfinite(torch.tensor(e["return_mean"])) for e in evals)


@pytest.mark.parametrize("mode", [True, "reduce-overhead"])
def test_compiled_update_on_cuda_matches_eager(mode):
    """``compile`` (and CUDA graphs through ``reduce-overhead``) take the same BC update as eager on a GPU."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    td = env.rollout(40, break_when_any_done=False).reshape(-1).to("cuda")
    agents = []
    for compiled in (False, mode):
        torch.manual_seed(0)
        agents.append(make_agent("bc", env, {"hidden_sizes": [8], "batch_size": 8, "compile": compiled}, action_key="action", device="cuda"))
        for k in range(5):
            agents[-1].update(td[8 * k: 8 * (k + 1)].clone())
    for (name, a), b in zip(agents[0].loss.state_dict().items(), agents[1].loss.state_dict().values()):
        assert a.device.type == "cuda"
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=name)


def test_a_gpu_decoder_acts_in_a_cpu_env():
    """The real MuJoCo env stays on the CPU while the decoder (shared with the model env) lives on the GPU."""
    from tensordict.nn import TensorDictModule

    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.envs import LatentActionTransform
    from torchrl_offhrl.models.cvae import CVAEDecoder

    torch.manual_seed(0)
    decoder = CVAEDecoder(11, 3, 2, hidden_sizes=(16,))
    outs = []
    for dev in ("cpu", "cuda"):
        env = make_gym_env("Hopper-v5", num_envs=2)
        env.append_transform(LatentActionTransform(decoder.to(dev)))
        env.set_seed(0)
        policy = TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 2), 0.5), in_keys=["observation"], out_keys=["latent_action"])
        td = env.rollout(5, policy, break_when_any_done=False)
        assert td["action"].device.type == "cpu"
        outs.append(td)
    torch.testing.assert_close(outs[0]["action"], outs[1]["action"], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("algo,decoder", [("moc", "discard"), ("sac", "keep")])
def test_transfer_run_on_cuda(algo, decoder, hopper_file, tmp_path, monkeypatch):
    """Both phases on the GPU: the offline phase on the model env, then the real env (on the CPU) through the collector."""
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    cfg = _cfg(algo, hopper_file, tmp_path, "cuda", 1)
    cfg["transfer"].update({"task": "backward", "online_frames": 128, "num_envs": 2, "eval_every_frames": 64, "decoder": decoder})
    s = train(cfg, progress=False)
    evals = json.loads((Path(s["run_dir"]) / "evals.json").read_text())
    assert [e["phase"] for e in evals][-3:] == ["online"] * 3 and evals[-1]["task"] == "backward"
    assert s["frames"] == 64 + 128 and all(torch.isfinite(torch.tensor(e["return_mean"])) for e in evals)


def _captured_and_eager(algo, extra, updates, batch=8):
    return pendulum_agents(algo, "cudagraphs", (False, True), extra, updates=updates, batch=batch, device="cuda")


@pytest.mark.parametrize("algo", ["bc", "iql"])
def test_captured_update_on_cuda_matches_eager(algo):
    """cudagraphs=true replays the whole update (loss, backward, Adam, target step) as one CUDA graph: BC's and IQL's (no sampling inside) match eager."""
    (eager, m_eager), (captured, m_captured) = _captured_and_eager(algo, {}, updates=8)
    assert set(captured.__dict__["_step_fns"]) == {None} and type(captured.__dict__["_step_fns"][None]).__name__ == "CudaGraphModule"
    assert captured.__dict__["_step_fns"][None].counter == 3  # 2 eager warm-up updates, captured at the 3rd; updates 4-8 were replays
    for (name, a), b in zip(eager.loss.state_dict().items(), captured.loss.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=name)
    for a, b in zip(m_eager, m_captured):
        assert a.keys() == b.keys()
        for k in a:
            if k != "updates":
                torch.testing.assert_close(torch.as_tensor(a[k]).float(), torch.as_tensor(b[k]).float(), rtol=1e-4, atol=1e-5, msg=k)


@pytest.mark.parametrize("algo,extra,forms", [("cql", {"policy_eval_start": 5, "num_random": 2}, {True, False}),
                                              ("td3bc", {}, {True, False})])
def test_captured_update_on_cuda_captures_each_form(algo, extra, forms):
    """CQL's behaviour-cloning phase and TD3+BC's delayed actor are Python branches: each is its own captured graph, and both learn."""
    _, (captured, metrics) = _captured_and_eager(algo, extra, updates=12)
    fns = captured.__dict__["_step_fns"]
    assert set(fns) == forms and all(f.counter == 3 for f in fns.values())  # each form captured, then replayed
    if algo == "cql":
        assert [float(m["train/bc_phase"]) for m in metrics] == [1.0] * 5 + [0.0] * 7
    else:
        assert ["train/loss_actor" in m for m in metrics] == [False, True] * 6
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    torch.manual_seed(0)
    fresh = make_agent(algo, env, {"hidden_sizes": [8], "batch_size": 8, **extra}, action_key="action")
    for name, b in captured.loss.state_dict().items():
        assert torch.isfinite(b).all(), name
    assert any(not torch.equal(a, b.cpu()) for (name, a), b in zip(fresh.loss.state_dict().items(), captured.loss.state_dict().values())
               if "actor_network_params" in name)  # the replayed updates moved the actor
    state = captured.state_dict()
    assert captured.steps == 12 and state["steps"] == 12
    # the captured run resumes on the CPU: capturable flags reset, the update runs there
    cpu = make_agent(algo, env, {"hidden_sizes": [8], "batch_size": 8, **extra}, action_key="action")
    cpu.load_state_dict(torch.utils._pytree.tree_map(lambda t: t.cpu() if torch.is_tensor(t) else t, state))
    assert cpu.steps == 12 and not any(g["capturable"] for o in cpu.optimizers() for g in o.param_groups)
    cpu.update(env.rollout(8, break_when_any_done=False).reshape(-1))


def _seed_batches(algo, extra, cudagraphs_values, seeds=(4, 5, 6), updates=8, batch=8):
    """One SeedBatch of ``algo`` on Pendulum per value of ``cudagraphs``, the agents of each built from the same seeds, each
    batch given the same ``updates`` stacked minibatches; returns ``[(seed batch, [per-seed metrics per update])]``."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.agents.seeds import SeedBatch
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Pendulum-v1")
    td = env.rollout(updates * batch * len(seeds), break_when_any_done=False).reshape(-1).to("cuda")
    out = []
    for value in cudagraphs_values:
        agents = []
        for s in seeds:
            torch.manual_seed(s)
            agents.append(make_agent(algo, env, {"hidden_sizes": [8], "batch_size": batch, "cudagraphs": value, **extra},
                                     action_key="action", device="cuda"))
        sb = SeedBatch(agents)
        per = len(seeds) * batch
        out.append((sb, [sb.update(td[per * k: per * (k + 1)].reshape(len(seeds), batch).clone()) for k in range(updates)]))
    return out


@pytest.mark.parametrize("algo", ["bc", "iql"])
def test_captured_seed_batch_on_cuda_matches_eager(algo):
    """cudagraphs=true captures the seeds' vmapped update (losses, backward, one Adam step for all seeds, target step) as a
    CUDA graph: for BC and IQL (no sampling inside) every seed's weights and metrics match the eager seed batch's."""
    (eager, m_eager), (captured, m_captured) = _seed_batches(algo, {}, (False, True))
    fns = captured.worker.__dict__["_step_fns"]
    assert set(fns) == {None} and type(fns[None]).__name__ == "CudaGraphModule" and fns[None].counter == 3
    assert "_step_fns" not in eager.worker.__dict__ or type(eager.worker.__dict__["_step_fns"][None]).__name__ != "CudaGraphModule"
    eager.sync(), captured.sync()
    for a_e, a_c in zip(eager.agents, captured.agents):
        for (name, a), b in zip(a_e.loss.state_dict().items(), a_c.loss.state_dict().values()):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=name)
    for per_e, per_c in zip(m_eager, m_captured):
        for a, b in zip(per_e, per_c):
            for k in a:
                if k != "updates":
                    torch.testing.assert_close(torch.as_tensor(a[k]).float(), torch.as_tensor(b[k]).float(), rtol=1e-4, atol=1e-5, msg=k)
    # the seeds stay distinct: each started from its own weights and still differs from the others
    s0, s1 = (captured.agents[i].loss.state_dict() for i in (0, 1))
    assert any(v.is_floating_point() and not torch.equal(v, s1[k]) for k, v in s0.items())


def test_captured_seed_batch_on_cuda_captures_cql_forms_and_restacks():
    """CQL's seed batch captures its behaviour-cloning and CQL forms as two graphs; stacking again (as after loading
    checkpoints) drops them, and the next updates capture again and keep learning, finite."""
    ((sb, metrics),) = _seed_batches("cql", {"policy_eval_start": 5, "num_random": 2}, (True,), updates=12)
    fns = sb.worker.__dict__["_step_fns"]
    assert set(fns) == {True, False} and all(f.counter == 3 for f in fns.values())
    assert [float(m[0]["train/bc_phase"]) for m in metrics] == [1.0] * 5 + [0.0] * 7
    sb.sync()
    before = [{k: v.clone() for k, v in a.loss.state_dict().items()} for a in sb.agents]
    sb.stack()
    assert "_step_fns" not in sb.worker.__dict__
    from torchrl_offhrl.data import make_gym_env

    td = make_gym_env("Pendulum-v1").rollout(4 * 24, break_when_any_done=False).reshape(-1).to("cuda")
    for k in range(4):
        sb.update(td[24 * k: 24 * (k + 1)].reshape(3, 8).clone())
    sb.sync()
    assert sb.worker.__dict__["_step_fns"][False].counter == 3
    for b, a in zip(before, sb.agents):
        now = a.loss.state_dict()
        assert all(torch.isfinite(v).all() for v in now.values())
        assert any(not torch.equal(b[k], now[k]) for k in b)
