"""Online SAC in the real Gymnasium env, to make D4RL-style behaviour policies.

D4RL's protocol: "expert" is a fully trained SAC policy, "medium" a checkpoint
of the same run stopped at about a third of the expert's return. This module
trains that run with TorchRL's :class:`~torchrl.objectives.SACLoss`, evaluates
it every ``eval_every`` environment steps and keeps every evaluated actor as a
small state dict, so the medium and expert levels are picked afterwards from
one run (:func:`pick_checkpoint`).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn

from ..data.collect import make_gym_env
from ..modules.options import mlp
from ..utils import atomic_write

__all__ = ["evaluate_policy", "first_episode_mask", "make_behaviour_actor", "pick_checkpoint", "train_behaviour_sac"]


def make_behaviour_actor(obs_dim: int, act_dim: int, low, high, hidden=(256, 256)):
    """SAC's tanh-Gaussian actor: ``observation`` -> ``action`` (+ ``action_log_prob``).

    Call it inside ``torchrl.envs.utils.set_exploration_type`` to choose
    between sampling (``RANDOM``, D4RL's stochastic data) and the mean
    (``DETERMINISTIC``).

    Examples:
        >>> import torch
        >>> actor = make_behaviour_actor(3, 2, -torch.ones(2), torch.ones(2), hidden=(8,))
        >>> from tensordict import TensorDict
        >>> actor(TensorDict(observation=torch.zeros(4, 3), batch_size=[4]))["action"].shape
        torch.Size([4, 2])
    """
    from torchrl.modules import ProbabilisticActor, TanhNormal

    net = nn.Sequential(mlp(obs_dim, 2 * act_dim, hidden, activation="relu"), NormalParamExtractor())
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": torch.as_tensor(low, dtype=torch.float32), "high": torch.as_tensor(high, dtype=torch.float32)},
        return_log_prob=True,
    )


def first_episode_mask(done: torch.Tensor) -> torch.Tensor:
    """``[E, T]`` bool: the steps of each env's first episode (up to and including its first ``done``).

    Examples:
        >>> first_episode_mask(torch.tensor([[False, True, False], [False, False, False]]))
        tensor([[ True,  True, False],
                [ True,  True,  True]])
    """
    done = done.int()
    return torch.cumsum(done, dim=1) - done == 0


@torch.no_grad()
def evaluate_policy(env, policy, episodes: int, max_steps: int = 1000, deterministic: bool = True, seed: int | None = None, return_rollout: bool = False):
    """Returns of the first episode of each of ``env``'s parallel envs.

    ``env`` is a batched TorchRL env with ``batch_size=[episodes]`` (e.g.
    :func:`~torchrl_offhrl.data.make_gym_env` with ``num_envs=episodes``),
    possibly auto-resetting: only rewards up to each env's first ``done``
    count. Returns a float tensor ``[episodes]`` (and the ``[episodes, T]``
    rollout when ``return_rollout``).
    """
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    if env.batch_size.numel() != episodes:
        raise ValueError(f"evaluate_policy: env has batch size {tuple(env.batch_size)}, expected [{episodes}]")
    if seed is not None:
        env.set_seed(seed)
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(mode):
        td = env.rollout(max_steps, policy, break_when_any_done=False, auto_cast_to_device=True)
    reward = td.get(("next", "reward")).reshape(episodes, -1)
    done = td.get(("next", "done")).reshape(episodes, -1)
    alive = first_episode_mask(done)
    returns = (reward * alive).sum(1).cpu()
    return (returns, td) if return_rollout else returns


def train_behaviour_sac(
    env_id: str,
    out_dir: str | Path,
    total_steps: int = 200_000,
    init_random_steps: int = 5_000,
    eval_every: int = 10_000,
    eval_episodes: int = 10,
    batch_size: int = 256,
    hidden=(256, 256),
    lr: float = 3e-4,
    gamma: float = 0.99,
    tau: float = 0.005,
    frames_per_batch: int = 50,
    seed: int = 0,
    progress: bool = True,
) -> list[dict]:
    """Train SAC online in ``env_id`` and save an actor snapshot at every evaluation.

    Writes ``out_dir/actor_<steps>.pt`` (actor state dict, atomic) and
    ``out_dir/evals.json`` (one record per evaluation: steps, stochastic and
    deterministic return mean/std over ``eval_episodes``, wall time). One
    gradient update per environment step (updates are done in groups of
    ``frames_per_batch``). Returns the list of evaluation records.
    """
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.modules import MLP, ValueOperator
    from torchrl.objectives import SACLoss, SoftUpdate
    from tqdm.auto import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    env = make_gym_env(env_id, num_envs=1)
    env.set_seed(seed)
    eval_env = make_gym_env(env_id, num_envs=eval_episodes)
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec
    act_dim = spec.shape[-1]
    low = spec.space.low.reshape(-1, act_dim)[0]
    high = spec.space.high.reshape(-1, act_dim)[0]
    actor = make_behaviour_actor(obs_dim, act_dim, low, high, hidden)
    qnet = MLP(in_features=obs_dim + act_dim, out_features=1, num_cells=list(hidden), activation_class=nn.ReLU)
    qvalue = ValueOperator(qnet, in_keys=["observation", "action"])
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", delay_actor=False, delay_qvalue=True, action_spec=spec)
    loss.make_value_estimator(gamma=gamma)
    updater = SoftUpdate(loss, tau=tau)
    opt_actor = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=lr)
    opt_q = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr)
    opt_alpha = torch.optim.Adam([loss.log_alpha], lr=lr)
    rb = ReplayBuffer(storage=LazyTensorStorage(total_steps), batch_size=batch_size)

    collector = Collector(
        env,
        actor,
        frames_per_batch=frames_per_batch,
        total_frames=total_steps,
        init_random_frames=init_random_steps,
        split_trajs=False,
        auto_register_policy_transforms=False,  # the envs are built with the transforms they need
    )
    records: list[dict] = []
    t0 = time.time()
    steps = 0
    bar = tqdm(total=total_steps, desc=f"SAC {env_id}", disable=not progress, unit="step")
    for batch in collector:
        batch = batch.reshape(-1)
        rb.extend(batch)
        steps += batch.numel()
        bar.update(batch.numel())
        if steps >= init_random_steps:
            for _ in range(batch.numel()):
                sample = rb.sample()
                losses = loss(sample)
                opt_q.zero_grad()
                opt_actor.zero_grad()
                opt_alpha.zero_grad()
                (losses["loss_qvalue"] + losses["loss_actor"] + losses["loss_alpha"]).backward()
                opt_q.step()
                opt_actor.step()
                opt_alpha.step()
                updater.step()
        if steps % eval_every < frames_per_batch and steps >= eval_every:
            rec = {"steps": steps, "wall_s": round(time.time() - t0, 1)}
            for det in (False, True):
                rets = evaluate_policy(eval_env, actor, eval_episodes, deterministic=det, seed=10_000 + steps)
                tag = "deterministic" if det else "stochastic"
                rec[tag] = {"mean": float(rets.mean()), "std": float(rets.std())}
            records.append(rec)
            with atomic_write(out / f"actor_{steps}.pt") as tmp:
                torch.save(actor.state_dict(), tmp)
            with atomic_write(out / "evals.json") as tmp:
                Path(tmp).write_text(json.dumps({"env_id": env_id, "seed": seed, "hidden": list(hidden), "evals": records}, indent=1))
            bar.set_postfix(ret=f"{rec['stochastic']['mean']:.0f}")
            bar.write(f"[{steps}] stochastic {rec['stochastic']['mean']:.1f} ± {rec['stochastic']['std']:.1f}  deterministic {rec['deterministic']['mean']:.1f}  ({rec['wall_s']} s)")
    bar.close()
    collector.shutdown()
    return records


def pick_checkpoint(records: list[dict], target: float | None = None, key: str = "stochastic") -> dict:
    """The evaluation record for a level: the best return (``target=None``) or the return closest to ``target``."""
    if not records:
        raise ValueError("pick_checkpoint: no evaluation records")
    if target is None:
        return max(records, key=lambda r: r[key]["mean"])
    return min(records, key=lambda r: abs(r[key]["mean"] - target) if math.isfinite(r[key]["mean"]) else float("inf"))
