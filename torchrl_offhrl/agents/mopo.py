"""MOPO (Yu et al., 2020): SAC on short model rollouts with an uncertainty-penalised reward, mixed with the dataset's transitions."""
from __future__ import annotations

import inspect

import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

from .registry import register_agent
from .sac import SACAgent

__all__ = ["MOPOAgent"]


@register_agent("mopo")
class MOPOAgent(SACAgent):
    """SAC whose minibatches mix model rollouts with the dataset's own transitions, as MOPO's policy optimisation does.

    The model env supplies MOPO's rollouts: branched from dataset states
    (``model_env.reset_states=any``), ``model_env.horizon`` steps long, each
    step's reward penalised by ``model_env.reward_penalty`` times the
    members' discrepancy (``configs/algo/mopo.yaml`` sets these to the
    official code's values). Each gradient step draws ``real_ratio`` of its
    minibatch from the dataset (MOPO's and MBPO's 5% by default) and the
    rest from the replay of model rollouts, so the critic also sees real,
    unpenalised transitions. The dataset's rewards get the reward scale the
    model env's rewards get (the loop passes it to :meth:`use_dataset`).

    The dataset's actions are real actions: with ``real_ratio > 0`` the agent
    must act in them (``ablation.no_cvae=true``, as ``algo=mopo`` sets).

    MOPO's rollout schedule (``rollout_freq``, default None: SAC's own, one
    model frame per ``utd_ratio`` of a gradient step). MOPO's code does not
    step the model once per gradient step: every ``rollout_freq`` (1,000)
    gradient steps it branches one ``horizon``-step rollout from each of
    ``rollout_batch_size`` (50,000) dataset states with the current policy,
    and its replay keeps the last ``model_retain_rollouts`` (5) rollouts.
    With ``rollout_freq`` set, each batch the agent collects is one rollout
    of every env of the model env, whose envs are MOPO's rollout batch (a
    run's config gives their count as ``algo.rollout_batch_size`` and the run
    builds the model env with that many; without it, ``collector.num_envs``):
    ``frames_per_batch`` is the envs times the env's ``horizon``, each batch
    is followed by ``rollout_freq`` gradient steps (``utd_ratio``
    is set from them), and the replay holds ``model_retain_rollouts``
    batches (``buffer_size`` is set from it). No random-action frames come
    first (``init_random_frames`` must be 0): MOPO rolls out its policy from
    the start.
    """

    #: MOPO's rollout schedule is the model env's (its envs are the rollout batch, its horizon the rollout length): an
    #: agent rebuilt to act in the real env (``offhrl evaluate``) takes SAC's schedule, which only collection reads
    training_only_keys = ("rollout_freq", "rollout_batch_size", "model_retain_rollouts")
    #: the transition entries the SAC loss reads, taken from both sources
    TRANSITION_KEYS = ("observation", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated"))

    def __init__(self, env, *, real_ratio: float = 0.05, rollout_freq: int | None = None, rollout_batch_size: int | None = None,
                 model_retain_rollouts: int = 5, **kwargs):
        if rollout_batch_size is not None and int(rollout_batch_size) != int(env.batch_size.numel()):
            raise ValueError(f"algo.rollout_batch_size={rollout_batch_size}: the model env has {env.batch_size.numel()} envs; the run "
                             "builds it with that many (recipes.train), a model env of your own must have as many")
        if rollout_freq is not None:
            horizon = getattr(getattr(env, "base_env", env), "horizon", None)
            if horizon is None:
                raise ValueError("algo.rollout_freq (MOPO's rollout schedule) needs a model env with a horizon (PessimisticModelEnv)")
            if int(rollout_freq) < 1 or int(model_retain_rollouts) < 1:
                raise ValueError(f"algo.rollout_freq and algo.model_retain_rollouts must be >= 1 (gradient steps per rollout, rollouts "
                                 f"kept), got {rollout_freq} and {model_retain_rollouts}")
            if kwargs.get("init_random_frames", 0):
                raise ValueError("algo.rollout_freq: MOPO rolls out its own policy from the start; set algo.init_random_frames=0")
            sac = inspect.signature(SACAgent.__init__).parameters
            superseded = sorted(k for k in ("frames_per_batch", "utd_ratio", "buffer_size") if k in kwargs and kwargs[k] != sac[k].default)
            if superseded:
                raise ValueError(f"algo.rollout_freq sets {', '.join('algo.' + k for k in superseded)} from MOPO's rollout schedule (a "
                                 "rollout of every env per batch, rollout_freq gradient steps after it, model_retain_rollouts kept): "
                                 "leave them at SAC's defaults, or give algo.rollout_freq=null for SAC's schedule")
            rollout = int(env.batch_size.numel()) * int(horizon)  # one rollout of every env: MOPO's rollout batch x its length
            kwargs.update(frames_per_batch=rollout, utd_ratio=int(rollout_freq) / rollout, buffer_size=int(model_retain_rollouts) * rollout,
                          init_random_frames=0)
        super().__init__(env, **kwargs)
        if not 0.0 <= float(real_ratio) < 1.0:
            raise ValueError(f"algo.real_ratio must be in [0, 1) (the share of each minibatch drawn from the dataset), got {real_ratio}")
        self.real_ratio = float(real_ratio)
        batch = self.replay_buffer.batch_size
        self.real_batch = round(batch * self.real_ratio)
        self.model_batch = batch - self.real_batch
        # the model rollouts' replay (the same storage) hands out the model's share of each minibatch
        self.replay_buffer = ReplayBuffer(storage=self.replay_buffer.storage, batch_size=self.model_batch)
        self.dataset_buffer = None

    def use_dataset(self, data, reward_scale: float = 1.0) -> None:
        """Keep the dataset's transitions (an :class:`~torchrl_offhrl.data.OfflineDataset` or a TensorDict; rewards times
        ``reward_scale``, as the model env's) to mix into each minibatch."""
        if not self.real_batch:
            return
        td = data[:]  # an OfflineDataset or a TensorDict of transitions
        if self.action_key not in td.keys(True):
            raise ValueError(f"algo.real_ratio mixes the dataset's transitions, whose actions are real, but this agent acts in "
                             f"{self.action_key!r}: give ablation.no_cvae=true (act in real actions), or algo.real_ratio=0")
        td = td.select(*self.TRANSITION_KEYS, self.action_key).clone()
        td.set(("next", "reward"), td.get(("next", "reward")) * float(reward_scale))
        # beside the model rollouts' replay, on its device: the two halves of a minibatch are concatenated as they come
        self.dataset_buffer = ReplayBuffer(storage=LazyTensorStorage(len(td), device=self.replay_buffer.storage.device), batch_size=self.real_batch)
        self.dataset_buffer.extend(td)

    def minibatch(self):
        """A minibatch of ``batch_size``: ``real_ratio`` of it from the dataset, the rest from the model rollouts' replay."""
        if self.dataset_buffer is None:
            return self.replay_buffer.sample()
        model = self.replay_buffer.sample().select(*self.TRANSITION_KEYS, self.action_key)  # the dataset's buffer holds only these
        return torch.cat([model, self.dataset_buffer.sample()], 0)


    def store(self, batch) -> None:
        if self.real_batch and self.dataset_buffer is None:
            raise RuntimeError("MOPOAgent: call use_dataset(data, reward_scale) before training (the training loop does)")
        super().store(batch)
