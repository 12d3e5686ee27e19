"""Seeds as a batch dimension (torchrl_offhrl.agents.seeds.SeedBatch): the same per-seed training as separate agents."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.agents.seeds import SeedBatch
from torchrl_offhrl.data import make_gym_env

N, B, T = 3, 16, 6


@pytest.fixture(scope="module")
def env():
    return make_gym_env("Pendulum-v1")


def build(env, name, seed, **kw):
    torch.manual_seed(seed)
    return make_agent(name, env, {"hidden_sizes": [16, 16], "batch_size": B, **kw}, action_key="action")


def batches(seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (T, N, B)
    nxt = TensorDict(observation=torch.randn(*shape, 3, generator=g), reward=torch.randn(*shape, 1, generator=g),
                     done=torch.zeros(*shape, 1, dtype=torch.bool), terminated=torch.rand(*shape, 1, generator=g) < 0.1, batch_size=shape)
    return TensorDict(observation=torch.randn(*shape, 3, generator=g), action=torch.rand(*shape, 1, generator=g) * 2 - 1, next=nxt, batch_size=shape)


def float_state(agent):
    return {k: v for k, v in agent.loss.state_dict().items() if torch.is_tensor(v) and v.is_floating_point()}


def assert_seeds_are_their_separate_agents(separate, batched, fresh, rtol, atol, moment, moment_rtol, moment_atol):
    """After ``batched.sync()``: each seed's tensors (weights, target networks, temperature) and Adam ``moment`` equal its
    separate agent's, the agents did learn (the check compares trained weights, not initial ones: ``fresh`` are the
    untrained agents), and the seeds stay different agents (seed 4's weights are not seed 5's)."""
    moved = 0.0
    for a, b, f in zip(separate, batched.agents, fresh):
        sa, sb, s0 = float_state(a), float_state(b), float_state(f)
        assert sa.keys() == sb.keys()
        for k in sa:
            torch.testing.assert_close(sb[k], sa[k], rtol=rtol, atol=atol)
            moved = max(moved, float((sa[k] - s0[k]).abs().max()))
        for oa, ob in zip(a.optimizers(), b.optimizers()):  # Adam's moments, slice by slice
            for pa, pb in zip((p for g in oa.param_groups for p in g["params"]), (p for g in ob.param_groups for p in g["params"])):
                if pa in oa.state:
                    torch.testing.assert_close(ob.state[pb][moment], oa.state[pa][moment], rtol=moment_rtol, atol=moment_atol)
    assert moved > 1e-4
    assert any(not torch.allclose(float_state(batched.agents[0])[k], float_state(batched.agents[1])[k]) for k in float_state(batched.agents[0]))


@pytest.mark.parametrize("name,kw", [("bc", {}), ("iql", {}), ("iql", {"actor": "tanh_mean_gaussian"}),
                                     ("td3bc", {"policy_noise": 0.0, "policy_update_delay": 2})])
def test_seed_batch_trains_each_seed_as_its_own_agent(env, name, kw):
    # N agents updated one by one, and the same N agents (same seeds) updated as one batched computation, on the same
    # per-seed minibatches: every weight, target network and optimiser state agrees up to float rounding
    seeds = [4, 5, 6]
    separate = [build(env, name, s, **kw) for s in seeds]
    batched = SeedBatch([build(env, name, s, **kw) for s in seeds])
    data = batches()
    for t in range(T):
        sep_metrics = [a.update(data[t, i]) for i, a in enumerate(separate)]
        bat_metrics = batched.update(data[t])
        for m_sep, m_bat in zip(sep_metrics, bat_metrics):
            assert set(m_sep) == set(m_bat)
            for k in m_sep:
                torch.testing.assert_close(torch.as_tensor(m_bat[k], dtype=torch.float32), torch.as_tensor(m_sep[k], dtype=torch.float32),
                                           rtol=1e-4, atol=1e-5)
    batched.sync()
    assert all(a.steps == b.steps == T for a, b in zip(separate, batched.agents))
    assert_seeds_are_their_separate_agents(separate, batched, [build(env, name, s, **kw) for s in seeds], 1e-4, 1e-5, "exp_avg_sq", 1e-3, 1e-9)


def test_seed_batch_resumes_from_the_agents_states(env):
    # stack() after loading each seed's checkpoint continues exactly where N separate agents continue
    seeds, data = [4, 5, 6], batches(1)
    first = SeedBatch([build(env, "iql", s) for s in seeds])
    for t in range(3):
        first.update(data[t])
    first.sync()
    states = [a.state_dict() for a in first.agents]
    resumed = [build(env, "iql", s) for s in seeds]
    for a, st in zip(resumed, states):
        a.load_state_dict(st)
    separate = [build(env, "iql", s) for s in seeds]
    for a, st in zip(separate, states):
        a.load_state_dict(st)
    batched = SeedBatch(resumed)
    for t in range(3, T):
        batched.update(data[t])
        for i, a in enumerate(separate):
            a.update(data[t, i])
    batched.sync()
    for a, b in zip(separate, batched.agents):
        for k, v in float_state(a).items():
            torch.testing.assert_close(float_state(b)[k], v, rtol=1e-4, atol=1e-5)


def test_seed_batch_stacks_each_seed_s_optimiser_moments_scalar_parameters_too(env):
    """Stacking trained agents (as after loading checkpoints) gives every parameter's Adam moments a seed dimension, also
    a scalar parameter's (CQL's temperature ``log_alpha``: its moments are 0-dim, and were once taken from seed 4 alone
    for all seeds, which a fused GPU Adam refused); ``sync`` hands each seed its own slice back."""
    import threading

    data = batches(2)
    agents = [build(env, "cql", s, policy_eval_start=0) for s in (4, 5, 6)]
    for i, a in enumerate(agents):
        for t in range(2):  # each its own data: different moments
            a.update(data[t, i])
    agents[0].__dict__["_step_fns"] = {None: threading.Lock()}  # e.g. a captured update (a CUDA stream): not copyable
    batched = SeedBatch(agents)
    assert "_step_fns" not in batched.worker.__dict__ and isinstance(agents[0].__dict__["_step_fns"][None], type(threading.Lock()))
    scalars = 0
    for w_opt, opts in zip(batched.worker.optimizers(), zip(*(a.optimizers() for a in agents))):
        for j, wp in enumerate(p for g in w_opt.param_groups for p in g["params"]):
            own = [[p for g in o.param_groups for p in g["params"]][j] for o in opts]
            if "exp_avg" not in opts[0].state.get(own[0], {}):  # not stepped yet
                continue
            scalars += own[0].dim() == 0
            for name in ("exp_avg", "exp_avg_sq"):
                assert w_opt.state[wp][name].shape == wp.shape == (3, *own[0].shape)
                torch.testing.assert_close(w_opt.state[wp][name], torch.stack([o.state[q][name] for o, q in zip(opts, own)]))
    assert scalars >= 1
    batched.update(data[3])
    batched.sync()
    for i, a in enumerate(agents):  # seed i's own slice of every moment, scalars' included
        for o, w_opt in zip(a.optimizers(), batched.worker.optimizers()):
            for q, wp in zip((p for g in o.param_groups for p in g["params"]), (p for g in w_opt.param_groups for p in g["params"])):
                if "exp_avg" in w_opt.state.get(wp, {}):
                    assert o.state[q]["exp_avg"].shape == q.shape
                    torch.testing.assert_close(o.state[q]["exp_avg"], w_opt.state[wp]["exp_avg"][i])
                    torch.testing.assert_close(o.state[q]["exp_avg_sq"], w_opt.state[wp]["exp_avg_sq"][i])


def test_seed_batch_sampling_streams_and_refusals(env):
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    rb = ReplayBuffer(storage=LazyTensorStorage(100), batch_size=8)
    rb.extend(TensorDict(x=torch.arange(100.0), batch_size=[100]))
    gens = [torch.Generator().manual_seed(s) for s in (1, 2)]
    sb = SeedBatch([build(env, "bc", 4), build(env, "bc", 5)], generators=gens)
    outer = torch.get_rng_state()
    first = sb.sample(rb)
    assert torch.equal(torch.get_rng_state(), outer)  # the global RNG is left alone
    assert first.batch_size == (2, 8)
    # each seed's stream is its own generator's: the same draws as a separate sampler seeded alike
    for i, s in enumerate((1, 2)):
        torch.manual_seed(s)
        assert torch.equal(first["x"][i], rb.sample()["x"])
    assert not torch.equal(first["x"][0], first["x"][1])
    with pytest.raises(ValueError, match="leading dimension"):
        sb.update(batches()[0, 0])
    with pytest.raises(TypeError, match="one class"):
        SeedBatch([build(env, "bc", 4), build(env, "iql", 5)])
    with pytest.raises(ValueError, match="agree on cudagraphs"):
        SeedBatch([build(env, "bc", 4), build(env, "bc", 5, cudagraphs=True)])
    with pytest.raises(ValueError, match="compile=False"):
        SeedBatch([build(env, "bc", 4, compile=True), build(env, "bc", 5, compile=True)])
    with pytest.raises(ValueError, match="share one config"):
        SeedBatch([build(env, "bc", 4), make_agent("bc", env, {"hidden_sizes": [8], "batch_size": B}, action_key="action")])
    from torchrl.objectives import CQLLoss

    plain = [build(env, "cql", 4), build(env, "cql", 5)]
    for a in plain:
        a.loss.__class__ = CQLLoss  # TorchRL's own loss reads .data: refused, with the reason
    with pytest.raises(NotImplementedError, match="vmap forbids"):
        SeedBatch(plain)


@pytest.mark.parametrize("name", ["bc", "iql", "cql", "td3bc"])
def test_seed_batch_reads_its_constants_from_the_loss_not_the_networks_own_buffers(env, name):
    """A TorchRL loss's networks keep buffers of their own beside the loss's copies, and ``loss.to(device)`` leaves them
    behind (on a GPU they stay on the CPU: the seed batch's update then failed). The constants every seed shares (the
    data's observation statistics) must come from the loss: with the networks' own copies poisoned (NaN), every seed's
    update is still its separate agent's."""
    separate = [build(env, name, s, **({"policy_noise": 0.0} if name == "td3bc" else {})) for s in (4, 5, 6)]
    batched = SeedBatch([build(env, name, s, **({"policy_noise": 0.0} if name == "td3bc" else {})) for s in (4, 5, 6)],
                        randomness="same" if name == "cql" else "different")
    poisoned = 0
    for net in ("actor_network", "qvalue_network", "value_network"):
        m = getattr(batched.worker.loss, net, None)
        for n, b in (m.named_buffers() if m is not None else ()):
            if n.endswith(("loc", "scale")):
                b.data.fill_(float("nan"))
                poisoned += 1
    assert poisoned and batched._shared_params is not None
    data = batches()[0]
    torch.manual_seed(0)
    metrics = batched.update(data.clone())
    assert all(torch.isfinite(torch.as_tensor(v)).all() for m in metrics for v in m.values())
    if name != "cql":  # CQL's draws inside the loss differ from separate agents' (the CQL test covers its equivalence)
        batched.sync()
        for i, a in enumerate(separate):
            a.update(data[i].clone())
            for k, v in float_state(a).items():
                torch.testing.assert_close(float_state(batched.agents[i])[k], v, rtol=1e-4, atol=1e-5)


def test_batchable_cql_loss_is_torchrl_s_cql_loss_on_the_same_draws(env):
    """BatchableCQLLoss changes how the loss detaches (``.detach()`` for ``.data``), not what it computes: TorchRL's CQLLoss,
    from the same weights and the same RNG state, gives the same outputs and, after an update, the same weights."""
    from torchrl.objectives import CQLLoss

    class TorchRLCQLLoss(CQLLoss):  # TorchRL's loss as it is, with the agent's post-step hook as a no-op (no alpha bounds here)
        def clamp_log_alpha(self):
            pass

    ours, theirs = build(env, "cql", 4, policy_eval_start=1), build(env, "cql", 4, policy_eval_start=1)
    theirs.loss.__class__ = TorchRLCQLLoss
    data = batches()
    for t in range(3):  # a behaviour-cloning update, then two SAC-style ones
        outs = []
        for a in (ours, theirs):
            torch.manual_seed(7 + t)
            outs.append(a.update(data[t, 0]))
        for k in outs[1]:
            torch.testing.assert_close(torch.as_tensor(outs[0][k]), torch.as_tensor(outs[1][k]), rtol=0, atol=0)
    for k, v in float_state(theirs).items():
        torch.testing.assert_close(float_state(ours)[k], v, rtol=0, atol=0)


def test_seed_batch_trains_cql_seeds_as_separate_agents_on_the_same_draws(env):
    """CQL batched (its random actions and policy samples drawn once for all seeds, ``randomness="same"``) equals N separate
    agents that each draw from the same RNG state; with ``randomness="different"`` (the default) each seed draws its own."""
    seeds, data = [4, 5, 6], batches()
    separate = [build(env, "cql", s, policy_eval_start=2) for s in seeds]
    batched = SeedBatch([build(env, "cql", s, policy_eval_start=2) for s in seeds], randomness="same")
    for t in range(T):  # two behaviour-cloning updates, then SAC-style ones with the CQL penalty and the Lagrange weight
        sep = []
        for i, a in enumerate(separate):
            torch.manual_seed(100 + t)
            sep.append(a.update(data[t, i]))
        torch.manual_seed(100 + t)
        bat = batched.update(data[t])
        for m_sep, m_bat in zip(sep, bat):
            for k in m_sep:
                torch.testing.assert_close(torch.as_tensor(m_bat[k], dtype=torch.float32), torch.as_tensor(m_sep[k], dtype=torch.float32),
                                           rtol=1e-4, atol=1e-5)
    batched.sync()
    moved = 0.0
    for a, b, fresh in zip(separate, batched.agents, [build(env, "cql", s) for s in seeds]):
        for k, v in float_state(a).items():
            torch.testing.assert_close(float_state(b)[k], v, rtol=1e-4, atol=1e-5)
            moved = max(moved, float((v - float_state(fresh)[k]).abs().max()))
    assert moved > 1e-4  # trained weights were compared, not initial ones
    own = SeedBatch([build(env, "cql", s) for s in seeds])  # each seed its own draws: the seeds' losses differ even on one minibatch
    m = own.update(torch.stack([data[0, 0]] * 3))
    losses = [float(x["train/loss_cql"]) for x in m]
    assert all(torch.isfinite(torch.tensor(losses))) and len(set(losses)) == 3


def _count_seeds_evaluations(monkeypatch) -> list:
    """Record each SeedsEvaluation.prepare call (its number of runs), and let Hopper batch its evaluations as a task whose
    episodes never end early would (the registry says it terminates, so real runs evaluate its seeds one by one)."""
    import dataclasses

    import torchrl_offhrl.registry as registry
    from torchrl_offhrl.recipes.evaluation import SeedsEvaluation

    calls, own, task_of = [], SeedsEvaluation.prepare, registry.task_of
    monkeypatch.setattr(SeedsEvaluation, "prepare", lambda self, policies: (calls.append(len(policies)), own(self, policies))[1])
    monkeypatch.setattr(registry, "task_of", lambda env: dataclasses.replace(task_of(env), terminates=False))
    return calls


def test_train_seeds_gives_each_seed_the_records_of_its_own_run(hopper_file, cache, tmp_path, monkeypatch):
    # `offhrl train --seeds 4 5` against two separate `offhrl train seed=S`: the same evaluation records and weights per seed,
    # each in its own run directory; then a longer budget resumes both from their checkpoints, batched again. The batch's
    # evaluations after the first run as one rollout of both seeds' policies (SeedsEvaluation), each seed's from its own
    # run's start states: the records match the separate runs' (a wrong block's start states would not)
    import json
    from pathlib import Path

    prepared = _count_seeds_evaluations(monkeypatch)
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.seed_runs import seed_configs, train_seeds
    from torchrl_offhrl.recipes.train import train

    def cfg(out, *extra):
        return compose("offline_train", ["algo=iql", f"dataset={hopper_file}", f"out_root={out}", "algo.hidden_sizes=[32,32]", "algo.batch_size=32",
                                         "train.total_updates=60", "eval.every_updates=30", "eval.episodes=2", "eval.max_steps=30", *extra])

    separate = [train(cfg(tmp_path / "sep", f"seed={s}"), progress=False) for s in (4, 5)]
    batched = train_seeds(cfg(tmp_path / "bat"), [4, 5], progress=False)
    for a, b in zip(separate, batched):
        assert Path(a["run_dir"]).name == Path(b["run_dir"]).name  # the same default name: algo, env, data, seed
        ra = json.loads((Path(a["run_dir"]) / "evals.json").read_text())
        rb = json.loads((Path(b["run_dir"]) / "evals.json").read_text())
        assert [r["updates"] for r in ra] == [r["updates"] for r in rb] == [0, 30, 60]
        for x, y in zip(ra, rb):
            assert y["return_mean"] == pytest.approx(x["return_mean"], rel=1e-3, abs=1e-2)
        wa = torch.load(Path(a["run_dir"]) / "checkpoint.pt", weights_only=True)["agent"]["loss"]
        wb = torch.load(Path(b["run_dir"]) / "checkpoint.pt", weights_only=True)["agent"]["loss"]
        for k, v in wa.items():
            if torch.is_tensor(v) and v.is_floating_point():
                torch.testing.assert_close(wb[k], v, rtol=1e-4, atol=1e-5)
    assert prepared == [2, 2]  # the evaluations at 30 and 60 updates, both seeds in one rollout
    r4 = json.loads((Path(batched[0]["run_dir"]) / "evals.json").read_text())
    r5 = json.loads((Path(batched[1]["run_dir"]) / "evals.json").read_text())
    assert r4[-1]["return_mean"] != r5[-1]["return_mean"]  # two seeds, two agents
    more = train_seeds(cfg(tmp_path / "bat", "train.total_updates=90"), [4, 5], progress=False)
    assert [s["updates"] for s in more] == [90, 90]
    assert [r["updates"] for r in json.loads((Path(more[0]["run_dir"]) / "evals.json").read_text())] == [0, 30, 60, 90]
    assert [c["run_dir"] for c in seed_configs({"seed": 0, "run_dir": "x", "seeds": [1]}, [4, 5])] == ["x/seed4", "x/seed5"]
    with pytest.raises(ValueError, match="distinct"):
        seed_configs({}, [4, 4])
    with pytest.raises(NotImplementedError, match="one seed per run"):  # SAC online, in the real env: one run per seed
        train_seeds(compose("offline_train", ["algo=sac", "train.online=true", f"dataset={hopper_file}"]), [4, 5])
    from torchrl_offhrl.recipes.seed_runs import batchable, refusal
    from torchrl_offhrl.utils import to_plain

    # refused from the config, before any run is prepared: MOC's policy average, a compiled loss; MOReL's KL-penalised PPO batches
    assert batchable(to_plain(compose("offline_train", ["algo=morel", f"dataset={hopper_file}"])))
    assert "policy_ema" in refusal(to_plain(compose("offline_train", ["algo=moc", "algo.policy_ema=0.1", f"dataset={hopper_file}"])))
    assert "compile" in refusal(to_plain(compose("offline_train", ["algo=iql", "algo.compile=true", f"dataset={hopper_file}"])))
    assert batchable(to_plain(compose("offline_train", ["algo=ppo", f"dataset={hopper_file}"])))


# ------------------------------------------------------------------ on-policy agents (PPO, MOC) on an env
E_ON, T_ON = 2, 16
ON_POLICY = {"ppo": {"max_grad_norm": 0.5}, "moc": {"max_grad_norm": 0.5, "eta": 0.5},
             # MOReL's trust region: PPO's adaptive KL penalty, a target low enough that the coefficient moves in these updates
             "ppo_kl": {"max_grad_norm": 0.5, "loss_type": "kl", "dtarg": 1e-4}}


def build_on_policy(env, name, seed, dtype=torch.float32):
    torch.manual_seed(seed)
    agent = make_agent(name.split("_")[0], env, {"hidden_sizes": [16, 16], "frames_per_batch": E_ON * T_ON, "minibatch_size": 8,
                                                 "epochs": 2, "fused_adam": False, **ON_POLICY[name]}, action_key="action")
    if dtype != torch.float32:  # the same initial weights, in double precision
        agent.loss.to(dtype)
        for opt in agent.optimizers():
            opt.state.clear()
    return agent


def as_double(td):
    return td.apply(lambda x: x.double() if x.is_floating_point() else x)


def on_policy_batch(env, agents, seed=0):
    """``[N, E, T]``: each seed's own rollouts (E episodes of T steps) with its own policy, in its own transformed env."""
    from torchrl.envs import TransformedEnv

    out = []
    for i, a in enumerate(agents):
        e = a.attach(TransformedEnv(env.base_env if isinstance(env, TransformedEnv) else env))
        runs = []
        for j in range(E_ON):
            e.set_seed(seed + 10 * i + j)
            torch.manual_seed(seed + 10 * i + j)
            with torch.no_grad():
                runs.append(e.rollout(T_ON, a.policy, break_when_any_done=False))
        out.append(torch.stack(runs))
    return torch.stack(out)


def test_batchable_kl_loss_is_torchrl_s_kl_penalty_loss_on_the_same_draws(env):
    """BatchableKLPENPPOLoss moves the KL coefficient's adaptation out of the forward pass, not what is computed. With the
    coefficient held, TorchRL's KLPENPPOLoss from the same weights, batches, shuffles and RNG state gives the same losses
    and weights, update after update; its adaptation rule gives the same coefficient as ``adapt_beta`` on every branch.
    (Adapting, TorchRL's gradient differs: its ``beta.data *= ...`` also rewrites the tensor autograd saved, so the
    penalty's gradient uses the coefficient already adapted to that minibatch, not the one its loss value used.) In double
    precision, as the seed-batch checks below: Adam's first steps are about lr x the gradient's sign, and the first
    minibatches' actor gradients are ~1e-9, where float32's rounding of the two sums decides the sign."""
    from torchrl.objectives import KLPENPPOLoss

    from torchrl_offhrl.agents.ppo import BatchableKLPENPPOLoss

    collector = build_on_policy(env, "ppo_kl", 4)
    ours, theirs = build_on_policy(env, "ppo_kl", 4, torch.float64), build_on_policy(env, "ppo_kl", 4, torch.float64)
    theirs.loss.__class__ = KLPENPPOLoss  # the agent's observe_minibatch then leaves the coefficient to TorchRL's forward
    assert isinstance(ours.loss, BatchableKLPENPPOLoss)
    for a in (ours, theirs):
        a.loss.increment = a.loss.decrement = 1.0
        a.loss.beta.fill_(0.7)
    for step in range(3):
        data = as_double(on_policy_batch(env, [collector], seed=step)[0])
        outs = []
        for a in (ours, theirs):
            a.generator = torch.Generator().manual_seed(step)
            torch.manual_seed(11 + step)
            outs.append(a.update(data.clone()))
        for k in ("train/loss_objective", "train/loss_critic", "train/kl_approx"):
            assert outs[0][k] == pytest.approx(outs[1][k], rel=1e-9, abs=1e-12), (k, outs[0][k], outs[1][k])
    for k, v in float_state(theirs).items():
        torch.testing.assert_close(float_state(ours)[k], v, rtol=1e-9, atol=1e-11)
    # the rule, on a minibatch the trained policy has moved away from (KL > 0): up, down, unchanged
    with torch.no_grad():
        ours.prepare(data)
    mb = data.reshape(-1)[:16]
    torch.manual_seed(0)
    kl = float(ours.loss(mb.clone())["kl"])
    assert kl > 0
    for dtarg, want in ((kl / 10, 2.0), (kl * 10, 0.5), (kl, 1.0)):
        got = []
        for a in (ours, theirs):
            a.loss.dtarg, a.loss.increment, a.loss.decrement = dtarg, 2.0, 0.5
            a.loss.beta.fill_(1.0)
            torch.manual_seed(0)
            out = a.loss(mb.clone())
            a.observe_minibatch(out)  # ours adapts here; TorchRL's already did in its forward
            got.append(float(a.loss.beta))
        assert got == [want, want], (dtarg, got)


def poison_network_buffers(*roots) -> int:
    """NaN into every ``loc``/``scale`` buffer reachable from ``roots`` (modules, and objects such as a value estimator
    holding them) that is not one of the first root's (a loss's) own tensors: the networks' own copies, which a TorchRL
    loss keeps beside its own and ``loss.to(device)`` leaves on the CPU, so that on a GPU they must never be read.
    Returns how many were poisoned."""
    own = {id(t) for t in TensorDict.from_module(roots[0], as_module=False).values(True, True)}
    seen, count = set(), 0

    def visit(obj):
        nonlocal count
        if id(obj) in seen or obj is None:
            return
        seen.add(id(obj))
        if isinstance(obj, torch.nn.Module):
            for name, b in obj.named_buffers(recurse=False):
                if name in ("loc", "scale") and id(b) not in own and b.is_floating_point():
                    b.data.fill_(float("nan"))
                    count += 1
            children = list(obj._modules.values())
        else:
            children = []
        children += [v for v in vars(obj).values() if isinstance(v, torch.nn.Module) or type(v).__name__.endswith("Estimate")
                     or type(v).__name__.endswith("GAE")]
        for c in children:
            visit(c)

    for r in roots:
        visit(r)
    return count


@pytest.mark.parametrize("name", ["ppo", "moc", "ppo_kl"])
def test_on_policy_seed_batch_updates_each_seed_as_its_own_agent(env, name):
    # the same per-seed batches and shuffles, and (randomness="same") the same draws inside the loss (MOC's z): each seed's
    # weights and Adam moments after two batched updates are its separate agent's, with gradients clipped per seed. In
    # double precision: Adam's first steps are about lr * sign(gradient), so float32's rounding of the batched products
    # would move weights whose gradient is near 0 by up to lr, and the check could not tell that from a wrong update
    from torchrl_offhrl.agents.seeds import OnPolicySeedBatch

    seeds = [4, 5, 6]
    actors = [build_on_policy(env, name, s) for s in seeds]  # float32: they collect the batches
    separate = [build_on_policy(env, name, s, torch.float64) for s in seeds]
    batched = OnPolicySeedBatch([build_on_policy(env, name, s, torch.float64) for s in seeds], randomness="same",
                                generators=[torch.Generator().manual_seed(i) for i in range(3)])
    for i, a in enumerate(separate):
        a.generator = torch.Generator().manual_seed(i)
    # the networks' own copies of the shared constants (CPU-bound on a GPU) must not be read: poisoned, nothing changes
    poisoned = poison_network_buffers(batched.worker.loss, batched.worker.loss.value_estimator)
    assert poisoned > 0 if name == "moc" else poisoned == 0  # TorchRL's PPO losses are not functional: no copies
    for step in range(2):
        data = as_double(on_policy_batch(env, actors, seed=step))
        state = torch.get_rng_state()
        got = batched.update(data.reshape(-1, T_ON))  # the collector's [N * E, T]
        want = []
        for i, a in enumerate(separate):
            torch.set_rng_state(state)
            want.append(a.update(data[i].clone()))
        for g, w in zip(got, want):
            assert set(g) == set(w)  # every metric a single run logs (PPO's explained_variance is [1] per seed)
            assert g["updates"] == w["updates"] == 2 * (E_ON * T_ON // 8)
            for k in ("train/loss_objective", "train/loss_critic") + (("train/kl",) if name == "ppo_kl" else ()):
                assert g[k] == pytest.approx(w[k], rel=1e-6, abs=1e-9), (k, g[k], w[k])
    if name == "ppo_kl":  # each seed's KL coefficient followed its own minibatches' KLs, and it did move
        betas = [float(a.loss.beta) for a in separate]
        torch.testing.assert_close(batched.worker.loss.beta, torch.tensor(betas, dtype=torch.float64))
        assert all(b != 1.0 for b in betas)
    batched.sync()
    assert_seeds_are_their_separate_agents(separate, batched, [build_on_policy(env, name, s, torch.float64) for s in seeds],
                                           1e-9, 1e-11, "exp_avg", 1e-8, 1e-12)


@pytest.mark.parametrize("name", ["ppo", "moc"])
def test_seed_batched_policy_acts_as_each_seed_s_policy(env, name):
    # deterministic: each seed's envs get exactly its own policy's actions; sampled, each seed draws its own noise
    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_offhrl.agents.seeds import OnPolicySeedBatch

    agents = [build_on_policy(env, name, s) for s in (4, 5, 6)]
    data = on_policy_batch(env, agents)  # [N, E, T]: states each seed's policy meets
    step = data[..., 3].exclude("next").reshape(-1)  # one step of the N * E envs, as a collector hands it over
    batched = OnPolicySeedBatch(agents)
    keys = ["action"] + (["option"] if name == "moc" else [])
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        out = batched.policy(step.clone()).reshape(3, E_ON)
        for i, a in enumerate(agents):
            mine = a.policy(step.reshape(3, E_ON)[i].clone())
            for k in keys:
                torch.testing.assert_close(out[i][k], mine[k], rtol=1e-5, atol=1e-6)
    # on a GPU, Agent.to moves the policy and the loss apart: their constant buffers stop sharing memory, and the batched
    # policy keeps the module's own (each seed holds the same), acting as before
    apart = [build_on_policy(env, name, s) for s in (4, 5, 6)]
    unshared = 0
    for a in apart:
        for n_, b in a.policy.named_buffers():
            if n_.rsplit(".", 1)[-1] in ("loc", "scale", "low", "high"):
                b.data = b.data.clone()
                unshared += 1
    assert unshared > 0
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        again = OnPolicySeedBatch(apart).policy(step.clone()).reshape(3, E_ON)
        for k in keys:
            torch.testing.assert_close(again[k], out[k])
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        same_state = step.reshape(3, E_ON)[0:1].expand(3, E_ON).reshape(-1).clone()
        a1 = batched.policy(same_state.clone())["action"].reshape(3, E_ON, -1)
    assert not torch.allclose(a1[0], a1[1])  # seeds 4 and 5 at the same states: their own draws (and weights)
    with pytest.raises(ValueError, match="seeds' envs"):
        batched.policy(step[:4].clone())
    with pytest.raises(TypeError, match="on-policy agents"):
        OnPolicySeedBatch([build(env, "bc", 4), build(env, "bc", 5)])
    if name == "ppo":  # TorchRL's own KL-penalised loss adapts its coefficient with data-dependent control flow: refused
        from torchrl.objectives import KLPENPPOLoss

        kl = [make_agent("ppo", env, {"hidden_sizes": [16, 16], "loss_type": "kl"}, action_key="action") for _ in range(2)]
        kl[0].loss.__class__ = kl[1].loss.__class__ = KLPENPPOLoss
        with pytest.raises(NotImplementedError, match="KLPENPPOLoss"):
            OnPolicySeedBatch(kl)


def test_train_seeds_batches_morel(hopper_file, cache, tmp_path):
    # `offhrl train algo=morel --seeds 4 5`: each seed clones the data's actions on its own first (pretrain.json), then the
    # seeds' KL-penalised PPO updates run as one, each seed's KL coefficient its own (stacked, adapted per seed)
    import json
    from pathlib import Path

    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.seed_runs import train_seeds

    cfg = compose("offline_train", ["algo=morel", f"dataset={hopper_file}", f"out_root={tmp_path}", "algo.hidden_sizes=[16,16]",
                                    "algo.frames_per_batch=64", "algo.minibatch_size=32", "algo.epochs=2", "algo.bc_init_steps=20",
                                    "algo.dtarg=1e-5", "ensemble.hidden_sizes=[16,16]", "ensemble.fit.max_steps=20",
                                    "cvae.hidden_sizes=[16,16]", "cvae.fit.max_steps=20", "collector.num_envs=4",
                                    "train.total_frames=128", "eval.every_frames=64", "eval.episodes=2", "eval.max_steps=20"])
    runs = train_seeds(cfg, [4, 5], progress=False)
    betas = []
    for r in runs:
        path = Path(r["run_dir"])
        assert json.loads((path / "pretrain.json").read_text())["bc_init_steps"] == 20
        assert [x["frames"] for x in json.loads((path / "evals.json").read_text())] == [0, 64, 128]
        betas.append(float(torch.load(path / "checkpoint.pt", weights_only=True)["agent"]["loss"]["beta"]))
    assert all(b != 1.0 for b in betas)  # each seed's coefficient adapted (dtarg 1e-5 is below any update's KL)


def test_train_seeds_batches_moc_on_one_model_env(hopper_file, cache, tmp_path, monkeypatch):
    # `offhrl train algo=moc --seeds 4 5`: one model env of 2 x 4 envs, each seed's 4 envs its own; each run directory
    # has its seed's records at the same frames as a separate run's, its own checkpoint, and resumes batched
    import json
    from pathlib import Path

    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.seed_runs import train_seeds
    from torchrl_offhrl.recipes.train import train

    def cfg(out, *extra):
        return compose("offline_train", ["algo=moc", f"dataset={hopper_file}", f"out_root={out}", "algo.hidden_sizes=[16,16]",
                                         "algo.frames_per_batch=64", "algo.minibatch_size=32", "algo.epochs=2",
                                         "ensemble.hidden_sizes=[16,16]", "ensemble.fit.max_steps=20", "cvae.hidden_sizes=[16,16]",
                                         "cvae.fit.max_steps=20", "collector.num_envs=4", "train.total_frames=128", "eval.every_frames=64",
                                         "eval.episodes=2", "eval.max_steps=20", "eval.sampled=true", *extra])

    separate = train(cfg(tmp_path / "sep", "seed=4"), progress=False)
    prepared = _count_seeds_evaluations(monkeypatch)  # MOC's evaluations as one rollout too (a latent policy, options, sampled)
    batched = train_seeds(cfg(tmp_path / "bat"), [4, 5], progress=False)
    assert prepared == [2, 2]
    monkeypatch.undo()  # Hopper as the registry has it: its seeds evaluate one by one (episodes end early)
    ra = json.loads((Path(separate["run_dir"]) / "evals.json").read_text())
    runs = [json.loads((Path(b["run_dir"]) / "evals.json").read_text()) for b in batched]
    assert Path(batched[0]["run_dir"]).name == Path(separate["run_dir"]).name
    for r in runs:
        assert [x["frames"] for x in r] == [x["frames"] for x in ra] == [0, 64, 128]
        assert [x["updates"] for x in r] == [x["updates"] for x in ra] == [0, 4, 8]  # 2 epochs x 2 minibatches per 64-frame batch
    assert runs[0][0]["return_mean"] == pytest.approx(ra[0]["return_mean"], rel=1e-4)  # the same untrained seed-4 agent
    assert runs[0][0]["return_mean_sampled"] == pytest.approx(ra[0]["return_mean_sampled"], rel=1e-4)
    # the later evaluations (one rollout of both seeds' policies) keep every key of a separate run's record
    assert all(set(x) == set(y) for r in runs for x, y in zip(r, ra))
    w = [torch.load(Path(b["run_dir"]) / "checkpoint.pt", weights_only=True)["agent"]["loss"] for b in batched]
    k = next(k for k, v in w[0].items() if torch.is_tensor(v) and v.is_floating_point() and v.dim() == 2)
    assert not torch.equal(w[0][k], w[1][k])  # two seeds, two agents
    logs = [json.loads((Path(b["run_dir"]) / "summary.json").read_text()) for b in batched]
    assert [s["frames"] for s in logs] == [128, 128]
    prepared = []
    from torchrl_offhrl.recipes.evaluation import SeedsEvaluation

    own = SeedsEvaluation.prepare
    monkeypatch.setattr(SeedsEvaluation, "prepare", lambda self, policies: (prepared.append(len(policies)), own(self, policies))[1])
    more = train_seeds(cfg(tmp_path / "bat", "train.total_frames=192"), [4, 5], progress=False)
    assert [s["frames"] for s in more] == [192, 192] and prepared == []
    assert [x["frames"] for x in json.loads((Path(more[1]["run_dir"]) / "evals.json").read_text())] == [0, 64, 128, 192]
    # a results script's own per-seed configs (run directories it names) batch alike; configs that differ otherwise do not
    from torchrl_offhrl.recipes.seed_runs import RunsApart, train_seed_configs
    from torchrl_offhrl.utils import to_plain

    named = [to_plain(cfg(tmp_path / "named", f"seed={s}", f"run_dir={tmp_path / 'named' / f'moc-seed{s}'}")) for s in (4, 5)]
    with pytest.raises(ValueError, match=r"differ beyond seed and run_dir \(\['algo'\]\)"):
        train_seed_configs([named[0], {**named[1], "algo": {**named[1]["algo"], "lr": 1e-3}}])
    train(named[0], progress=False)  # seed 4 finished alone: the two runs stand apart
    with pytest.raises(RunsApart, match="different steps") as apart:
        train_seed_configs(named, progress=False, catch_up=False)
    assert apart.value.steps == [128, 0] and apart.value.unit == "frames"
    # by default the run behind (seed 5, at its untrained evaluation) trains alone to seed 4's step, on its own schedule
    caught = train_seed_configs(named, progress=False)
    assert [s["frames"] for s in caught] == [128, 128]
    assert [x["frames"] for x in json.loads((tmp_path / "named" / "moc-seed5" / "evals.json").read_text())] == [0, 64, 128]
    # and from there the two go on as one batch
    longer = [{**c, "train": {**c["train"], "total_frames": 192}} for c in named]
    assert [s["frames"] for s in train_seed_configs(longer, progress=False)] == [192, 192]
    assert [x["frames"] for x in json.loads((tmp_path / "named" / "moc-seed5" / "evals.json").read_text())] == [0, 64, 128, 192]


# ------------------------------------------------------------------ off-policy agents (SAC, MOPO) on an env
def build_off_policy(env, name, seed, **kw):
    torch.manual_seed(seed)
    agent = make_agent(name, env, {"hidden_sizes": [16, 16], "batch_size": 8, "init_random_frames": 8, "frames_per_batch": 4,
                                   "buffer_size": 1000, "fused_adam": False, **kw}, action_key="action")
    agent.loss = agent.loss.double()
    return agent


def off_policy_batch(g, n, e):
    shape = (n, e, 1)
    nxt = TensorDict(observation=torch.randn(*shape, 3, generator=g, dtype=torch.float64), reward=torch.randn(*shape, 1, generator=g, dtype=torch.float64),
                     done=torch.zeros(*shape, 1, dtype=torch.bool), terminated=torch.rand(*shape, 1, generator=g) < 0.2, batch_size=shape)
    return TensorDict(observation=torch.randn(*shape, 3, generator=g, dtype=torch.float64),
                      action=torch.rand(*shape, 1, generator=g, dtype=torch.float64) * 2 - 1, next=nxt, batch_size=shape)


@pytest.mark.parametrize("name", ["sac", "mopo"])
def test_off_policy_seed_batch_updates_each_seed_as_its_own_agent(env, name):
    # each seed stores its part of the collected batch in its own replay buffer and samples its minibatches (MOPO: with
    # its share of the dataset) from its own generator; with randomness="same" (SAC's sampled actions are the draws a
    # separate agent makes from the same RNG state) every loss, weight, target critic, temperature and Adam moment after
    # three collected batches (the first only fills the buffers: init_random_frames) is its separate agent's
    from torchrl_offhrl.agents.seeds import OffPolicySeedBatch

    n, e, seeds = 3, 4, [4, 5, 6]
    dataset = off_policy_batch(torch.Generator().manual_seed(7), 1, 50)[0].reshape(-1)
    kw = {"real_ratio": 0.25} if name == "mopo" else {}

    def agents():
        out = [build_off_policy(env, name, s, **kw) for s in seeds]
        for a in out:
            a.use_dataset(dataset, reward_scale=0.5)
        return out

    separate = agents()
    batched = OffPolicySeedBatch(agents(), randomness="same", generators=[torch.Generator().manual_seed(i) for i in range(n)])
    own = [torch.Generator().manual_seed(i) for i in range(n)]
    g = torch.Generator().manual_seed(0)
    for step in range(3):
        data = off_policy_batch(g, n, e)
        state = torch.get_rng_state()
        got = batched.update(data.reshape(n * e, 1))  # the collector's [N * E, T]
        want = []
        for i, a in enumerate(separate):
            torch.set_rng_state(state)

            def sample(a=a, i=i):
                with torch.random.fork_rng(devices=[]):
                    torch.set_rng_state(own[i].get_state())
                    out = a.minibatch()
                    own[i].set_state(torch.get_rng_state())
                return out

            a.store(data[i])
            want.append(a.gradient_steps(data[i].numel(), sample))
        for gd, w in zip(got, want):
            assert set(gd) == set(w)
            assert gd["updates"] == w["updates"] == (0 if step == 0 else e)
            for k in w:
                assert gd[k] == pytest.approx(w[k], rel=1e-9, abs=1e-12), (k, gd[k], w[k])
    assert len(batched.agents[0].replay_buffer) == len(separate[0].replay_buffer) == 3 * e  # each seed its own frames
    assert batched.worker.replay_buffer is None  # the worker holds no copy of agent 0's buffer
    batched.sync()
    assert all(a.frames == b.frames == 3 * e for a, b in zip(separate, batched.agents))
    assert_seeds_are_their_separate_agents(separate, batched, [build_off_policy(env, name, s, **kw) for s in seeds],
                                           1e-9, 1e-12, "exp_avg", 1e-8, 1e-12)
    # a batch of the wrong width is refused with what it should be
    with pytest.raises(ValueError, match="the 3 seeds' envs"):
        batched.update(off_policy_batch(g, 1, 4).reshape(4, 1))


def test_train_seeds_batches_off_policy_agents_on_one_model_env(hopper_file, cache, tmp_path):
    # `offhrl train algo=mopo --seeds 4 5` (SAC whose minibatches mix the dataset's transitions; plain SAC takes the same
    # path, and the update rule of both is checked against separate agents above): one model env of
    # 2 x 4 envs; each seed's run has the records of a separate run at the same frames, its own replay buffer saved
    # with its checkpoint, and resumes batched
    import json
    from pathlib import Path

    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.seed_runs import train_seeds
    from torchrl_offhrl.recipes.train import train

    def cfg(out, *extra):
        # SAC's schedule (algo.rollout_freq=null): frames and updates counted as below; MOPO's own is tested in test_recipes
        return compose("offline_train", ["algo=mopo", f"dataset={hopper_file}", f"out_root={out}", "algo.hidden_sizes=[16,16]",
                                         "algo.rollout_freq=null", "algo.rollout_batch_size=null",
                                         "algo.frames_per_batch=8", "algo.batch_size=16", "algo.init_random_frames=16",
                                         "ensemble.hidden_sizes=[16,16]", "ensemble.fit.max_steps=20", "cvae.hidden_sizes=[16,16]",
                                         "cvae.fit.max_steps=20", "collector.num_envs=4", "train.total_frames=48", "eval.every_frames=24",
                                         "eval.episodes=2", "eval.max_steps=20", *extra])

    separate = train(cfg(tmp_path / "sep", "seed=4"), progress=False)
    batched = train_seeds(cfg(tmp_path / "bat"), [4, 5], progress=False)
    ra = json.loads((Path(separate["run_dir"]) / "evals.json").read_text())
    runs = [json.loads((Path(b["run_dir"]) / "evals.json").read_text()) for b in batched]
    assert Path(batched[0]["run_dir"]).name == Path(separate["run_dir"]).name
    for r in runs:
        assert [x["frames"] for x in r] == [x["frames"] for x in ra] == [0, 24, 48]
        # batches of 8 frames: steps (one per frame) from the batch that brings the 16th frame in: 16 at 24 frames, 40 at 48
        assert [x["updates"] for x in ra] == [0, 16, 40] and [x["updates"] for x in r] == [0, 16, 40]
        assert all(set(x) == set(y) for x, y in zip(r, ra))
    assert runs[0][0]["return_mean"] == pytest.approx(ra[0]["return_mean"], rel=1e-4)  # the same untrained seed-4 agent
    w = [torch.load(Path(b["run_dir"]) / "checkpoint.pt", weights_only=True)["agent"] for b in batched]
    assert [x["frames"] for x in w] == [48, 48]
    k = next(k for k, v in w[0]["loss"].items() if torch.is_tensor(v) and v.is_floating_point() and v.dim() == 2)
    assert not torch.equal(w[0]["loss"][k], w[1]["loss"][k])  # two seeds, two agents
    more = train_seeds(cfg(tmp_path / "bat", "train.total_frames=72"), [4, 5], progress=False)
    assert [s["frames"] for s in more] == [72, 72]
    r = json.loads((Path(more[1]["run_dir"]) / "evals.json").read_text())
    assert [x["frames"] for x in r] == [0, 24, 48, 72] and r[-1]["updates"] == 64  # resumed with its buffer: no random frames again


def test_seeds_batched_on_mopos_rollout_schedule_count_as_separate_runs(hopper_file, cache, tmp_path):
    """algo=mopo on its code's schedule, two seeds batched: the shared model env has 2 x rollout_batch_size envs, and each
    seed's run takes rollout_freq steps after each of its rollouts (4 envs x horizon 5 = 20 frames, 6 steps), as a
    separate run does."""
    import json
    from pathlib import Path

    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.seed_runs import train_seeds
    from torchrl_offhrl.recipes.train import train

    def cfg(out, *extra):
        return compose("offline_train", ["algo=mopo", f"dataset={hopper_file}", f"out_root={out}", "algo.hidden_sizes=[16,16]",
                                         "algo.rollout_batch_size=4", "algo.rollout_freq=6", "algo.batch_size=16", "model_env.horizon=5",
                                         "ensemble.hidden_sizes=[16,16]", "ensemble.fit.max_steps=20", "cvae.hidden_sizes=[16,16]",
                                         "cvae.fit.max_steps=20", "train.total_frames=40", "eval.every_frames=20", "eval.episodes=2",
                                         "eval.max_steps=20", *extra])

    separate = json.loads((Path(train(cfg(tmp_path / "sep", "seed=4"), progress=False)["run_dir"]) / "evals.json").read_text())
    for b in train_seeds(cfg(tmp_path / "bat"), [4, 5], progress=False):
        runs = json.loads((Path(b["run_dir"]) / "evals.json").read_text())
        assert [(x["frames"], x["updates"]) for x in runs] == [(x["frames"], x["updates"]) for x in separate] == [(0, 0), (20, 6), (40, 12)]
