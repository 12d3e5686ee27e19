"""The pessimistic MDP of the block-stacking tasks: learned transitions, the tasks' own goals and rewards."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Unbounded
from torchrl.envs import Transform

from ..blockstack import goals as G
from .pessimistic import PessimisticModelEnv

__all__ = ["BlockStackModelEnv", "SubGoalTracker", "replay_open_loop"]


class BlockStackModelEnv(PessimisticModelEnv):
    """:class:`PessimisticModelEnv` for the goal-conditioned block-stacking tasks (:mod:`torchrl_offhrl.blockstack.env`).

    The ensemble learns transitions only (``learn_reward=False``): the
    rewards, sub-goals and successes come from the shared functions of
    :mod:`torchrl_offhrl.blockstack.goals`, applied to the predicted states, so an
    agent sees the same task as in the real env. Episodes start from the
    dataset's initial states with a goal drawn uniformly (or from
    ``goal_probs``) and last ``horizon`` steps (25, the paper's); they end
    early only on a pessimistic termination (the members disagree beyond the
    threshold: reward ``-penalty``, the paper's 50; threshold at the 0.99
    quantile of the data's discrepancies by default).

    Writes the real env's keys: ``desired_goal`` (one-hot), ``achieved_goal``
    (success flags of every sub-goal), ``sub_goals`` (``[n_goals, d]``) and
    ``achieved_sub_goal``, besides :class:`PessimisticModelEnv`'s.

    Args:
        ensemble, data: as :class:`PessimisticModelEnv` (``data`` a block-stacking dataset).
        n_blocks: 2 or 3 (default: from the observation size).
        goal_probs: probabilities of the goals at reset (default uniform).
        penalty, quantile, horizon: the paper's 50, 0.99, 25 by default.
        **kwargs: the other arguments of :class:`PessimisticModelEnv`
            (``threshold``, ``discrepancy``, ``batch_size``, ``device``, ``seed``...).
    """

    needs_model_reward = False

    def __init__(self, ensemble, data, n_blocks: int | None = None, goal_probs=None, penalty: float = 50.0, quantile: float | None = 0.99,
                 horizon: int = 25, **kwargs):
        if n_blocks is None:
            n_blocks = G.blocks_for_obs_dim(data.observation_dim)
            if n_blocks is None:
                raise ValueError(f"observations of {data.observation_dim} entries are not of a block-stacking task "
                                 f"({G.obs_dim(2)}: 2 blocks, {G.obs_dim(3)}: 3 blocks)")
        self.n_blocks = G.check_blocks(n_blocks)
        if data.observation_dim != G.obs_dim(self.n_blocks):
            raise ValueError(f"the dataset's observations have {data.observation_dim} entries, the {n_blocks}-block task's {G.obs_dim(n_blocks)}")
        self.n_goals = G.n_goals(self.n_blocks)
        probs = torch.full((self.n_goals,), 1.0 / self.n_goals) if goal_probs is None else torch.as_tensor(goal_probs, dtype=torch.float64)
        if probs.shape != (self.n_goals,) or (probs < 0).any() or not probs.sum() > 0:
            raise ValueError(f"goal_probs must be {self.n_goals} non-negative numbers with a positive sum, got {goal_probs!r}")
        self._goal_probs = (probs / probs.sum()).double()
        kwargs.setdefault("termination_fn", None)  # the tasks never terminate: the horizon ends them
        if kwargs.get("reward_penalty"):
            raise ValueError("reward_penalty is not supported on the block-stacking tasks: their rewards are the goals' (0 / -1), "
                             "recomputed after the model's step; use the threshold's termination (model_env.pessimism)")
        super().__init__(ensemble, data, penalty=penalty, quantile=quantile, horizon=horizon, **kwargs)

    def _make_specs(self, data) -> None:
        super()._make_specs(data)
        B, dev = self.batch_size, self.device
        d = G.sub_goal_dim(self.n_blocks)
        self.observation_spec["desired_goal"] = Unbounded((*B, self.n_goals), dtype=torch.float32, device=dev)
        self.observation_spec["achieved_goal"] = Unbounded((*B, self.n_goals), dtype=torch.float32, device=dev)
        self.observation_spec["sub_goals"] = Unbounded((*B, self.n_goals, d), dtype=torch.float32, device=dev)
        self.observation_spec["achieved_sub_goal"] = Unbounded((*B, d), dtype=torch.float32, device=dev)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        out = super()._reset(tensordict, **kwargs)
        B = self.batch_size
        n = max(1, B.numel())
        k = torch.multinomial(self._goal_probs, n, replacement=True, generator=self._rng).to(self.device)
        out.set("desired_goal", torch.nn.functional.one_hot(k, self.n_goals).float().reshape(*B, self.n_goals))
        out.update(G.goal_fields(out.get("observation"), self.n_blocks))
        return out

    @torch.no_grad()
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = super()._step(tensordict)
        desired = tensordict.get("desired_goal")
        fields = G.goal_fields(out.get("observation"), self.n_blocks)
        reward = G.goal_reward(fields["achieved_goal"], desired).unsqueeze(-1)
        out.set("reward", torch.where(out.get("penalized"), torch.full_like(reward, -self.penalty), reward))
        out.set("desired_goal", desired.clone())
        out.update(fields)
        return out


class SubGoalTracker(Transform):
    """Follows each env's goal along its abstract demonstration: writes ``option`` and its ``sub_goal`` (the low level's goal).

    At reset the option is the first of the goal's sequence
    (:func:`~torchrl_offhrl.blockstack.goals.first_option` of ``desired_goal``);
    after each step it moves on when its sub-goal is met at s'
    (:func:`~torchrl_offhrl.blockstack.goals.next_option`), as the scripted data
    were collected. ``sub_goal`` is that option's row of ``sub_goals``. A
    flat agent conditioned on the low-level goal (the paper's SAC + HER in
    the CVAE's latent space) reads ``sub_goal``, and so does a
    goal-conditioned decoder (``LatentActionTransform(decoder,
    goal_key="sub_goal")``). Works on the real envs and on
    :class:`BlockStackModelEnv` alike.
    """

    def __init__(self, option_key: str = "option", sub_goal_key: str = "sub_goal"):
        super().__init__(in_keys=["desired_goal", "achieved_goal", "sub_goals"], out_keys=[option_key, sub_goal_key])
        self.option_key, self.sub_goal_key = option_key, sub_goal_key

    def transform_observation_spec(self, observation_spec):
        sub = observation_spec["sub_goals"]
        lead, n_goals = sub.shape[:-2], sub.shape[-2]
        observation_spec[self.option_key] = Bounded(0, n_goals - 1, lead, dtype=torch.int64, device=sub.device)
        observation_spec[self.sub_goal_key] = Unbounded((*lead, sub.shape[-1]), dtype=sub.dtype, device=sub.device)
        return observation_spec

    def _select(self, td: TensorDictBase, option: torch.Tensor) -> TensorDictBase:
        sub = td.get("sub_goals")
        td.set(self.option_key, option)
        td.set(self.sub_goal_key, sub.gather(-2, option[..., None, None].expand(*option.shape, 1, sub.shape[-1])).squeeze(-2))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        goal = tensordict_reset.get("desired_goal").argmax(-1)
        option = G.first_option(goal)
        if tensordict is not None and "_reset" in tensordict.keys() and self.option_key in tensordict.keys():
            keep = ~tensordict.get("_reset").reshape(option.shape)  # envs not reset keep their option
            option = torch.where(keep, tensordict.get(self.option_key), option)
        return self._select(tensordict_reset, option)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        option = tensordict.get(self.option_key)
        goal = tensordict.get("desired_goal").argmax(-1)
        return self._select(next_tensordict, G.next_option(option, goal, next_tensordict.get("achieved_goal")))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:  # on a stored batch: the option is recorded there
        return tensordict


def replay_open_loop(ensemble, episodes: TensorDictBase, n_blocks: int, threshold: float | None = None, kind: str = "variance") -> dict:
    """Replay recorded episodes' actions open loop through every member of ``ensemble``: how far the model drifts from the real env.

    ``episodes`` is ``[E, T]`` (whole episodes of a block-stacking dataset:
    ``observation``, ``action``, ``desired_goal``, ``("next", "observation")``,
    ``("next", "reward")``). Each member starts from each episode's first
    state and is fed the recorded actions on its own predicted states (as in
    the P-MDP, where one member makes a whole episode). Returns (tensors):

    * ``gripper_error`` / ``block_error``: ``[T]`` mean distance (m) between
      the predicted and the real gripper / block positions after each step
      (mean over members, episodes and blocks);
    * ``real_success``: ``[E]`` the episode reached its goal (high-level reward 0 at some step);
    * ``model_success``: ``[K, E]`` the member's path reached it (the task's
      functions on the predicted states; pessimism not applied);
    * ``cut_step``: ``[K, E]`` the first step (1-based) at which the members'
      disagreement on the path exceeds ``threshold`` (where the P-MDP would
      end the episode with the penalty), ``T + 1`` when never (or no threshold);
    * ``goal``: ``[E]`` the episodes' goals.
    """
    obs = episodes.get("observation").float()
    E, T, D = obs.shape
    actions = episodes.get("action").float()
    real = episodes.get(("next", "observation")).float()
    goal_onehot = episodes.get("desired_goal")[:, 0].float()
    K = ensemble.num_members
    members = torch.arange(K)
    state = obs[:, 0].expand(K, E, D)
    path, disc = [], []
    with torch.no_grad():
        for t in range(T):
            out = ensemble.predict(state.reshape(K * E, D), actions[:, t].repeat(K, 1))
            nxt = out["next_observation"].reshape(K, K, E, D)  # [member, whose path, E, D]
            disc.append(ensemble.discrepancy_of(out["delta"], kind).reshape(K, E))
            state = nxt[members, members]  # each member on its own path
            path.append(state)
    pred = torch.stack(path, 2)  # [K, E, T, D]
    dis = torch.stack(disc, 2)  # [K, E, T]
    gripper_error = torch.linalg.vector_norm(pred[..., 0:3] - real[..., 0:3], dim=-1).mean((0, 1))
    blocks_p, blocks_r = G.block_positions(pred, n_blocks), G.block_positions(real, n_blocks)
    block_error = torch.linalg.vector_norm(blocks_p - blocks_r, dim=-1).mean((0, 1, 3))
    flags = G.achieved_goal_flags(pred, n_blocks)  # [K, E, T, n_goals]
    model_success = (G.goal_reward(flags, goal_onehot[None, :, None, :]) == 0).any(-1)
    real_success = (episodes.get(("next", "reward")).reshape(E, T) == 0).any(-1)
    if threshold is None:
        cut = torch.full((K, E), T + 1)
    else:
        over = ~(dis <= threshold)  # NaN counts as over
        cut = torch.where(over.any(-1), over.float().argmax(-1) + 1, torch.full((K, E), T + 1))
    return {"gripper_error": gripper_error, "block_error": block_error, "real_success": real_success, "model_success": model_success,
            "cut_step": cut, "goal": goal_onehot.argmax(-1)}
