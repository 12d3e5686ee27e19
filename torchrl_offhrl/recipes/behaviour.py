"""Train a D4RL-style behaviour policy online in the real Gymnasium env (``scripts/train_behaviour.py``).

D4RL's protocol: "expert" is a fully trained SAC policy, "medium" a checkpoint
of the same run stopped at about a third of the expert's return. This module
runs that training (the learner: :class:`~torchrl_offhrl.agents.behaviour.BehaviourLearner`,
SAC through the SAC agents' gradient step, or CrossQ), evaluates it every
``eval_every`` environment steps and keeps every evaluated actor as a small
state dict, so the medium and expert levels are picked afterwards from one
run (:func:`~torchrl_offhrl.data.policies.actors.pick_checkpoint`,
:func:`~torchrl_offhrl.data.policies.ship_policy`).

Why its loop is not the recipe loop's (:mod:`~torchrl_offhrl.recipes.train`):
a behaviour run keeps *every* evaluated actor (the levels are chosen after
the run, by their returns), evaluates both the sampled and the mean policy
(D4RL's data is sampled), and its folder's format (``evals.json``,
``actor_<steps>.pt``, ``state/``) is what :func:`ship_policy` and the
shipped policies' cards name; the recipe loop's run directory, policy
selection and model-env settings do not apply to it.
"""
from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import torch

from ..agents.behaviour import BehaviourLearner
from ..data import make_gym_env
from ..data.policies.actors import algorithm_defaults, make_behaviour_actor
from ..data.policies.plots import plot_behaviour_run
from ..rollouts import evaluate_policy
from ..utils import atomic_write

__all__ = ["latest_state", "save_state", "train_behaviour", "train_behaviour_sac"]

_KEEP = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "truncated"))




def train_behaviour(
    env_id: str,
    out_dir: str | Path,
    algorithm: str = "sac",
    total_steps: int = 200_000,
    init_random_steps: int = 5_000,
    eval_every: int = 10_000,
    eval_episodes: int = 10,
    eval_max_steps: int = 1000,
    batch_size: int = 256,
    hidden=(256, 256),
    critic_hidden=None,
    lr: float | None = None,
    gamma: float = 0.99,
    tau: float = 0.005,
    frames_per_batch: int = 50,
    seed: int = 0,
    progress: bool = True,
    device=None,
) -> list[dict]:
    """Train a behaviour policy online in ``env_id``; save the actor at every evaluation; resume if interrupted.

    Args:
        algorithm: ``"sac"`` (TorchRL's :class:`~torchrl.objectives.SACLoss`,
            target critics with Polyak ``tau``, lr 3e-4) or ``"crossq"``
            (TorchRL's :class:`~torchrl.objectives.CrossQLoss`: batch
            renormalisation in the critic and no target critics; Adam lr
            1e-3 with beta1 0.5 and an actor/temperature update every 3
            critic updates, as published; the critic is ``critic_hidden``
            wide, 256 by default instead of the paper's 2048).
        total_steps: environment steps; one critic update per step (updates
            run in groups of ``frames_per_batch`` after ``init_random_steps``
            uniform-random steps).
        hidden / critic_hidden: layer widths of the actor / critic
            (``critic_hidden`` defaults to ``hidden``).
        lr: learning rate of every optimiser (default: the algorithm's).
        eval_max_steps: step limit of the evaluation episodes (the env's
            1000; smaller only for quick tests).
        device: where the networks, the updates and the replay buffer live
            (default CPU; e.g. ``"cuda"``). The MuJoCo env steps on the CPU;
            the saved actors are CPU tensors whatever the device.

    Writes, atomically:

    * ``out_dir/actor_<steps>.pt``: the actor's state dict at each evaluation;
    * ``out_dir/evals.json``: env id, algorithm, seed, widths and one record
      per evaluation (steps, stochastic and deterministic return mean/std
      over ``eval_episodes`` fresh episodes, wall time);
    * ``out_dir/curve.png``: the learning curve so far, with the D4RL medium
      band and expert target (:func:`~torchrl_offhrl.data.policies.plots.plot_behaviour_run`);
    * ``out_dir/state/``: everything needed to continue (networks,
      optimisers, temperature, replay buffer, counters, RNG), refreshed at
      every evaluation. Calling again with the same ``out_dir`` continues
      from there (with a larger ``total_steps`` it trains further); a call
      whose ``env_id``, ``algorithm``, widths, ``seed`` or training
      settings (``lr``, ``batch_size``, ``gamma``, ``tau`` (SAC only:
      CrossQ has no target critics), ``frames_per_batch``,
      ``init_random_steps``) differ from the saved run's is refused (a
      state saved before the settings were recorded is checked on the
      others, and keeps its optimisers' lr). ``device`` may change between
      calls.
      The environment restarts from a reset, which at most cuts one
      episode short.

    Returns the list of evaluation records.
    """
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from tqdm.auto import tqdm

    algorithm_defaults(algorithm)  # fail before touching out_dir
    dev = torch.device("cpu" if device is None else device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r}, but this torch build ({torch.__version__}) sees no CUDA GPU: "
                         "install a CUDA build of torch, or leave device unset to train on the CPU")
    hidden = tuple(hidden)
    critic_hidden = hidden if critic_hidden is None else tuple(critic_hidden)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    identity = {
        "env_id": env_id,
        "algorithm": algorithm,
        "hidden": list(hidden),
        "critic_hidden": list(critic_hidden),
        "seed": seed,
        "lr": algorithm_defaults(algorithm)["lr"] if lr is None else lr,
        "batch_size": batch_size,
        "gamma": gamma,
        "tau": tau,
        "frames_per_batch": frames_per_batch,
        "init_random_steps": init_random_steps,
    }

    state = None
    state_dir = latest_state(out)
    if state_dir is not None:  # a saved run: check it is this one, and whether anything is left to do
        state = torch.load(state_dir / "state.pt", map_location="cpu", weights_only=True)
        saved = state["identity"]
        unused = set() if algorithm_defaults(algorithm)["target_critics"] else {"tau"}  # CrossQ has no target critics
        diff = {k: (saved[k], v) for k, v in identity.items() if k in saved and k not in unused and saved[k] != v}
        if diff:
            raise ValueError(
                f"{out}: holds a {saved['algorithm']} run on {saved['env_id']} that differs from this call "
                f"in {diff} (saved, asked). Use another --out folder, or the saved settings to continue it."
            )
        if state["steps"] >= total_steps:
            return state["records"]

    torch.manual_seed(seed)
    env = make_gym_env(env_id, num_envs=1)
    env.set_seed(seed)
    eval_env = make_gym_env(env_id, num_envs=eval_episodes)
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec
    act_dim = spec.shape[-1]
    low = spec.space.low.reshape(-1, act_dim)[0].to(dev)  # the actor's tanh bounds live with it
    high = spec.space.high.reshape(-1, act_dim)[0].to(dev)
    actor = make_behaviour_actor(obs_dim, act_dim, low, high, hidden).to(dev)
    learner = BehaviourLearner(actor, obs_dim, act_dim, spec.to(dev), algorithm, critic_hidden, lr=lr, gamma=gamma, tau=tau, device=dev)
    rb = ReplayBuffer(storage=LazyTensorStorage(total_steps, device=dev), batch_size=batch_size)

    records: list[dict] = []
    steps = 0
    wall0 = 0.0
    if state is not None:
        learner.load_state_dict(state["learner"])
        if "lr" not in state["identity"]:  # an older state: its optimisers (now loaded) hold the lr in use
            identity["lr"] = learner.opt_q.param_groups[0]["lr"]
        if state["capacity"] == total_steps:
            rb.loads(state_dir / "replay")
        else:  # a longer run than the saved one: copy the saved transitions into the larger buffer
            saved_rb = ReplayBuffer(storage=LazyTensorStorage(state["capacity"]), batch_size=batch_size)  # on the CPU: one buffer on the device
            saved_rb.loads(state_dir / "replay")
            rb.extend(saved_rb.storage[: len(saved_rb)])
        torch.set_rng_state(state["rng"])
        if dev.type == "cuda" and state.get("cuda_rng") is not None:
            torch.cuda.set_rng_state(state["cuda_rng"], dev)
        records, steps, wall0 = state["records"], state["steps"], state["wall_s"]

    collector = Collector(
        env,
        actor,
        frames_per_batch=frames_per_batch,
        total_frames=total_steps - steps,
        init_random_frames=max(0, init_random_steps - steps),
        split_trajs=False,
        env_device="cpu",
        policy_device=dev,
        storing_device=dev,
        auto_register_policy_transforms=False,  # the envs are built with the transforms they need
    )
    t0 = time.time() - wall0
    bar = tqdm(total=total_steps, initial=steps, desc=f"{algorithm} {env_id}", disable=not progress, unit="step")
    for batch in collector:
        batch = batch.reshape(-1).select(*_KEEP, strict=False)
        rb.extend(batch)
        steps += batch.numel()
        bar.update(batch.numel())
        if steps >= init_random_steps:
            for _ in range(batch.numel()):
                learner.update(rb.sample())
        if steps % eval_every < frames_per_batch and steps >= eval_every:
            rec = {"steps": steps, "wall_s": round(time.time() - t0, 1)}
            for det in (False, True):
                rets = evaluate_policy(eval_env, actor, eval_episodes, max_steps=eval_max_steps, deterministic=det, seed=10_000 + steps)
                tag = "deterministic" if det else "stochastic"
                rec[tag] = {"mean": float(rets.mean()), "std": float(rets.std())}
            records.append(rec)
            with atomic_write(out / f"actor_{steps}.pt") as tmp:
                torch.save({k: v.cpu() for k, v in actor.state_dict().items()}, tmp)
            with atomic_write(out / "evals.json") as tmp:
                Path(tmp).write_text(json.dumps({**identity, "evals": records}, indent=1))
            save_state(
                out,
                rb,
                {
                    "identity": identity,
                    "learner": learner.state_dict(),
                    "rng": torch.get_rng_state(),
                    "cuda_rng": torch.cuda.get_rng_state(dev) if dev.type == "cuda" else None,
                    "records": records,
                    "steps": steps,
                    "capacity": total_steps,
                    "wall_s": time.time() - t0,
                },
            )
            try:  # a figure is a convenience: never lose a run to it
                plot_behaviour_run(out)
            except Exception as err:  # noqa: BLE001
                warnings.warn(f"{out}: could not draw curve.png ({err!r}); training goes on", stacklevel=2)
            bar.set_postfix(ret=f"{rec['stochastic']['mean']:.0f}")
            bar.write(f"[{steps}] stochastic {rec['stochastic']['mean']:.1f} ± {rec['stochastic']['std']:.1f}  deterministic {rec['deterministic']['mean']:.1f}  ({rec['wall_s']} s)")
    bar.close()
    collector.shutdown()
    eval_env.close()
    return records


def train_behaviour_sac(env_id: str, out_dir: str | Path, **kwargs) -> list[dict]:
    """:func:`train_behaviour` with ``algorithm="sac"``."""
    return train_behaviour(env_id, out_dir, algorithm="sac", **kwargs)


def latest_state(out: Path) -> Path | None:
    """The complete saved state of a run, if any (``state/``, or ``state.old/`` after a crash mid-swap)."""
    for name in ("state", "state.old"):
        if (out / name / "state.pt").is_file():
            return out / name
    return None


def save_state(out: Path, rb, state: dict) -> None:
    """Write the resumable state into ``state.tmp/``, then swap it in for ``state/``.

    ``state.pt`` is written last, so a folder without it is incomplete; the
    previous state is kept as ``state.old/`` until the new one is in place.
    """
    import shutil

    tmp, cur, old = out / "state.tmp", out / "state", out / "state.old"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    rb.dumps(tmp / "replay")
    with atomic_write(tmp / "state.pt") as f:
        torch.save(state, f)
    shutil.rmtree(old, ignore_errors=True)
    if cur.exists():
        cur.rename(old)
    tmp.rename(cur)
    shutil.rmtree(old, ignore_errors=True)
