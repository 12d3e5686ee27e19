"""Rolling a policy out in a batched env and reading episode returns: shared by data generation, behaviour training and the recipes.

Below ``data`` in the layer order: it only needs TorchRL envs.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict

__all__ = ["evaluate_policy", "first_episode_mask", "first_episodes_rollout", "full_reset_mask", "seed_each_env"]


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
def evaluate_policy(env, policy, episodes: int, max_steps: int = 1000, deterministic: bool = True, seed: int | None = None, return_rollout: bool = False,
                    stop_early: bool = True, env_seeds=None):
    """Returns of the first episode of each of ``env``'s parallel envs.

    ``env`` is a batched TorchRL env with ``batch_size=[episodes]`` (e.g.
    :func:`~torchrl_offhrl.data.make_gym_env` with ``num_envs=episodes``),
    possibly auto-resetting: only rewards up to each env's first ``done``
    count. Returns a float tensor ``[episodes]`` (and the ``[episodes, T]``
    rollout when ``return_rollout``). With ``deterministic=False`` and a
    ``seed``, the policy's samples are drawn from torch's RNG seeded with it
    (forked: the caller's RNG stream is left as it was), so a stochastic
    evaluation is as repeatable as a deterministic one.

    With ``stop_early`` and a ``seed`` (or ``env_seeds``) the rollout stops at the step where
    the last env ends its first episode (``T`` may then be below
    ``max_steps``): what comes after is never counted, so the returns and the
    first episodes' steps are those of the full ``max_steps`` rollout (the
    same actions, draws and states; ``tests/test_rollouts.py``), at the cost
    of the steps the first episodes take. Without a seed the env's state
    after the call is the next call's start, so the rollout runs all
    ``max_steps`` as it always did.

    ``env_seeds`` (one int per env) seeds env ``i`` of a gym vector env with
    ``env_seeds[i]`` instead of ``seed + i`` (:func:`seed_each_env`; e.g. the
    envs of several runs' evaluations in one env, each block with its own
    run's seeds); ``seed`` still seeds the draws.
    """
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    if env.batch_size.numel() != episodes:
        raise ValueError(f"evaluate_policy: env has batch size {tuple(env.batch_size)}, expected [{episodes}]")
    if env_seeds is not None:
        seed_each_env(env, env_seeds)
    elif seed is not None:
        env.set_seed(seed)
    mask = full_reset_mask(env)
    td0 = env.reset(mask) if mask is not None else env.reset()
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    seeded = not deterministic and seed is not None
    params = policy.parameters() if seeded and hasattr(policy, "parameters") else ()  # policy None: the env's random actions
    devices = [d for d in {p.device for p in params} if d.type == "cuda"]
    with torch.random.fork_rng(devices=devices, enabled=seeded), set_exploration_type(mode):
        if seeded:
            torch.manual_seed(seed)
        if stop_early and (seed is not None or env_seeds is not None):
            td = first_episodes_rollout(env, policy, max_steps, td0)
        else:
            td = env.rollout(max_steps, policy, tensordict=td0, auto_reset=False, break_when_any_done=False, auto_cast_to_device=True)
    reward = td.get(("next", "reward")).reshape(episodes, -1)
    done = td.get(("next", "done")).reshape(episodes, -1)
    alive = first_episode_mask(done)
    returns = (reward * alive).sum(1).cpu()
    return (returns, td) if return_rollout else returns


def seed_each_env(env, seeds) -> None:
    """Seed env ``i`` of ``env`` (a TorchRL-wrapped gym vector env, possibly transformed) with ``seeds[i]``.

    ``env.set_seed(s)`` resets the wrapped gym env with ``seed=s`` (TorchRL's ``GymEnv``), and a gym vector env seeds
    its env ``i`` with ``s + i``; this makes the same reset with one seed per env (gymnasium's ``reset(seed=[...])``), so a
    block of envs seeded ``s, s + 1, ...`` starts where an env of that block's size seeded ``s`` starts.
    """
    from torchrl.envs import TransformedEnv

    seeds = [int(x) for x in seeds]
    if len(seeds) != env.batch_size.numel():
        raise ValueError(f"seed_each_env: {len(seeds)} seeds for an env of batch size {tuple(env.batch_size)}")
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    base.reset(seed=seeds)


def first_episodes_rollout(env, policy, max_steps: int, tensordict):
    """``env.rollout(max_steps, policy, tensordict=tensordict, auto_reset=False, break_when_any_done=False)``, stopped at
    the step where every env has ended its first episode.

    The steps are TorchRL's own (``policy``, then ``env.step_and_maybe_reset``, the done envs reset as in a
    non-stopping rollout), so every step up to the stop is the full rollout's. TorchRL's ``break_when_all_done``
    is not this: it needs an env that can step some of its envs and not others (a gym vector env cannot). ``policy``
    None: the env's random actions (``env.rand_action``), as ``env.rollout`` takes them. Unlike ``env.rollout`` the
    policy is called as it is (no ``_make_compatible_policy`` wrapping: a TensorDict module is expected), and it runs
    on its parameters' device with the data moved there and back when that differs from the env's.
    """
    policy = env.rand_action if policy is None else policy
    params = list(policy.parameters()) if hasattr(policy, "parameters") else []
    policy_device = params[0].device if params else None
    cast = policy_device is not None and env.device is not None and policy_device != env.device
    ended = torch.zeros(env.batch_size, dtype=torch.bool, device=env.device)
    tds, td_ = [], tensordict
    for i in range(max_steps):
        if cast:
            td_ = td_.to(policy_device)
        td_.update(policy(td_))
        if cast:
            td_ = td_.to(env.device)
        if i == max_steps - 1:
            td = env.step(td_)
        else:
            td, td_ = env.step_and_maybe_reset(td_)
        tds.append(td)
        ended |= td.get(("next", "done")).reshape(env.batch_size)
        if bool(ended.all()):
            break
    out = torch.stack(tds, len(env.batch_size))
    out.refine_names(..., "time")  # as env.rollout names its time dimension
    return out


def full_reset_mask(env):
    """The ``reset()`` input that resets every env of ``env`` (after ``set_seed``: to its seeded state), or None.

    When some (not all) envs of a TorchRL-wrapped gym vector env ended their
    episode at the last step of the previous rollout, a plain ``reset()`` is a
    partial one: TorchRL's ``VecGymEnvTransform`` hands those envs the
    observation of their automatic reset instead of resetting them, so an
    evaluation would depend on the one before it. An explicit
    all-True ``"_reset"`` mask makes it a full reset; the transform only
    accepts one once the env has stepped (it compares the mask with the
    ``done`` it remembers from the last step), hence the check; before the
    first step a plain ``reset()`` is a full one (None is returned).
    """
    from torchrl.envs import Compose, TransformedEnv

    stale, inner = False, env
    while isinstance(inner, TransformedEnv):
        transforms = inner.transform if isinstance(inner.transform, Compose) else [inner.transform]
        stale |= any(type(t).__name__ == "VecGymEnvTransform" and t._memo.get("done") is not None for t in transforms)
        inner = inner.base_env
    if not stale:
        return None
    reset = torch.ones(env.full_done_spec["done"].shape, dtype=torch.bool, device=env.device)
    return TensorDict({"_reset": reset}, batch_size=env.batch_size, device=env.device)
