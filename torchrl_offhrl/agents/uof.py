"""The Universal Option Framework (UOF): DIOL over sub-goal options above a goal-conditioned DDPG + HER low level.

As the official UOF code runs it (``../shared/reference/block_stacking.md``),
on the goal-conditioned P-MDP and in the goal-conditioned CVAE's latent space:

* high level (:class:`~torchrl_offhrl.objectives.DIOLLoss`): ``Q(s, g, o)``
  for the state and the one-hot goal, one value per option (option ``o``
  pursues sub-goal ``o``). An option runs until its sub-goal is met (or the
  episode ends); then the high level picks again: epsilon-greedy on the
  target network with UOF's schedule (:func:`~torchrl_offhrl.objectives.uof_epsilon`),
  greedy at test. In a share ``demo_ratio`` of the training episodes (UOF:
  12 of 16) the options follow the goal's abstract demonstration instead
  (the env's :class:`~torchrl_offhrl.envs.SubGoalTracker`); every transition
  trains DIOL, which is off-policy in the options. The high level's reward
  is the env's (0 when the success flags equal the goal) where the running
  option is the goal's, else -1 (UOF's condition), and the penalty at a
  pessimistic termination.
* low level (:class:`~torchrl_offhrl.objectives.TwinDDPGLoss`): a
  deterministic actor ``pi(s, sub_goal)`` writing the latent action, twin
  critics, targets clamped to ``[-25, 0]``, HER on the sub-goal within
  option segments (:mod:`~torchrl_offhrl.agents.her`, TorchRL's
  ``HERReplayBuffer``, strategy 'future'). Exploration (training only): with
  probability ``0.2 (1 - sr_g)`` a uniform latent action, else Gaussian noise
  of ``0.05 (1 - sr_g)`` times the latent box's half-width, with ``sr_g`` an
  exponential average (rate 0.05) of the goal's success in the real-env
  evaluations (UOF's test success).
* both levels learn from the same rollouts: every collected batch goes into
  both replay buffers, then ``updates_per_frame`` gradient steps per frame
  (UOF: 40 low- and 40 high-level updates per cycle of 16 episodes x 25
  steps, i.e. 0.1), minibatches of 128, Adam 1e-3, and the targets follow
  with ``tau = 0.1`` after each step. The low level's critic and actor
  and the high level take one step of one optimiser per update (Adam treats
  each parameter on its own, and the actor's loss reaches the actor only).

Deviations from UOF, for an offline agent: the input normaliser uses the
dataset's statistics (UOF updates running ones), and HER draws 'future'
achieved sub-goals within the segment at ratio 0.8 (UOF: 4 achieved goals
per segment, relabelled copies of the prefix).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import TanhModule, ValueOperator
from torchrl.objectives import SoftUpdate

from ..blockstack import goals as G
from ..nets import GoalMLP
from ..objectives import DIOLLoss, TwinDDPGLoss, uof_epsilon
from .base import Agent, MetricMeans, action_box, adam
from .her import LOW_DONE, LOW_REWARD, ReplayBuffers, low_level_done, low_level_keys, prepare_low_level, sub_goal_her_buffer
from .registry import register_agent

__all__ = ["UOFAgent", "UOFPolicy", "goal_option_usage", "goal_networks", "plot_goal_option_usage"]

HIGH_REWARD = ("next", "high_reward")
_HIGH_KEYS = ("observation", "desired_goal", "option", ("next", "observation"), ("next", "desired_goal"), ("next", "achieved_goal"), HIGH_REWARD,
              ("next", "done"))


def goal_networks(env, action_key: str, goal_key: str, hidden_sizes, obs_loc=None, obs_scale=None, clip: float | None = 3.0,
                  last_layer_init: float | None = 3e-3, stochastic_actor: bool = False):
    """``(actor, qvalue)`` conditioned on the state and the goal ``goal_key`` (UOF's low level; SAC + HER with ``stochastic_actor``).

    Inputs are normalised with the dataset's statistics as UOF normalises:
    ``(x - mean) / (std + 0.01)`` clipped to ``[-3, 3]``; the goal (a
    sub-goal: finger, gripper and block coordinates) with the statistics of the
    same coordinates of the state. The actor is deterministic, squashed by
    TorchRL's ``TanhModule`` into the action box, or (``stochastic_actor``) a
    tanh-Gaussian; the critic writes ``state_action_value``.
    """
    from tensordict.nn import NormalParamExtractor

    from ..nets import tanh_gaussian_actor

    obs_dim = env.observation_spec["observation"].shape[-1]
    goal_dim = env.observation_spec[goal_key].shape[-1]
    act_dim, low, high = action_box(env, action_key)
    n_blocks = G.blocks_for_obs_dim(obs_dim)
    goal_loc = goal_scale = None
    if obs_loc is not None and n_blocks is not None and goal_dim == G.sub_goal_dim(n_blocks):
        goal_loc = G.achieved_sub_goal(torch.as_tensor(obs_loc, dtype=torch.float32), n_blocks)
        goal_scale = G.achieved_sub_goal(torch.as_tensor(obs_scale, dtype=torch.float32), n_blocks) + 0.01
    obs_scale = None if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32) + 0.01
    hidden = list(hidden_sizes)

    def net(extra, out):
        return GoalMLP(obs_dim, goal_dim, extra, out, hidden, "relu", obs_loc, obs_scale, goal_loc, goal_scale, clip=clip, last_layer_init=last_layer_init)

    if stochastic_actor:
        body = TensorDictSequential(TensorDictModule(net(0, 2 * act_dim), in_keys=["observation", goal_key], out_keys=["param"]),
                                    TensorDictModule(NormalParamExtractor(), in_keys=["param"], out_keys=["loc", "scale"]))
        actor = tanh_gaussian_actor(body, low, high, action_key)
    else:
        actor = TensorDictSequential(
            TensorDictModule(net(0, act_dim), in_keys=["observation", goal_key], out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=[action_key], low=low, high=high),
        )
    qvalue = ValueOperator(net(act_dim, 1), in_keys=["observation", goal_key, action_key], out_keys=["state_action_value"])
    return actor, qvalue


class UOFPolicy(TensorDictModuleBase):
    """UOF's rollout policy: keeps an option until its sub-goal is met, picks the next with DIOL, acts for its sub-goal.

    Reads ``observation``, ``desired_goal``, ``achieved_goal`` (success
    flags at s), ``sub_goals``, ``is_init``, ``prev_option`` and
    ``demo_episode`` (carried by :meth:`make_transforms`) and the env's
    demonstration ``option`` (:class:`~torchrl_offhrl.envs.SubGoalTracker`);
    writes ``option`` (replacing the demonstration's), ``option_start``,
    ``sub_goal`` (the option's row of ``sub_goals``: what the low level and
    the goal-conditioned decoder read), the action, ``("next",
    "prev_option")`` and ``("next", "demo_episode")``. Under
    ``ExplorationType.DETERMINISTIC``: greedy options, no demonstrations, the
    actor's action.

    ``oracle_options`` (a diagnostic, off in training and in every result):
    under ``DETERMINISTIC`` too, every episode follows the goal's abstract
    demonstration instead of DIOL's greedy picks, so an evaluation measures
    what the low level achieves when it is handed the right sub-goals in the
    right order (``experiments/diagnostics/uof_oracle_options.py``).
    """

    def __init__(self, diol: DIOLLoss, actor, low: torch.Tensor, high: torch.Tensor, num_options: int, action_key: str,
                 demo_ratio: float = 0.75, random_action_prob: float = 0.2, action_noise: float = 0.05):
        super().__init__()
        self.diol, self.actor = diol, actor
        self.num_options, self.action_key = int(num_options), action_key
        self.demo_ratio, self.random_action_prob, self.action_noise = float(demo_ratio), float(random_action_prob), float(action_noise)
        self.register_buffer("low", low.clone())
        self.register_buffer("high", high.clone())
        self.register_buffer("success_ema", torch.zeros(num_options))
        self.epsilon = 1.0
        self.oracle_options = False
        self.in_keys = ["observation", "desired_goal", "achieved_goal", "sub_goals", "option", "is_init", "prev_option", "demo_episode"]
        self.out_keys = ["option", "option_start", "sub_goal", action_key, ("next", "prev_option"), ("next", "demo_episode")]

    def make_transforms(self) -> list:
        """``[InitTracker, TensorDictPrimer(prev_option, demo_episode)]``: append them to every env the policy acts in."""
        from torchrl.data import Categorical, Unbounded
        from torchrl.envs import InitTracker, TensorDictPrimer

        return [InitTracker(init_key="is_init"),
                TensorDictPrimer({"prev_option": Categorical(self.num_options, shape=(), dtype=torch.int64),
                                  "demo_episode": Unbounded(shape=(), dtype=torch.bool)}, default_value=0, expand_specs=True)]

    def option_values(self, td: TensorDictBase) -> torch.Tensor:
        """``[..., num_options]``: the first target network's option values (UOF chooses options with the target network)."""
        with torch.no_grad():
            return self.diol.option_values(td, self.diol.target_value_network_params)[0]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get("observation")
        batch = obs.shape[:-1]
        is_init = td.get("is_init").reshape(batch)
        prev = td.get("prev_option").reshape(batch).long()
        goal = td.get("desired_goal").argmax(-1)
        repick = is_init | G.option_met(prev, td.get("achieved_goal"))
        greedy = self.option_values(td).argmax(-1)
        det = exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)
        demo = torch.full_like(is_init, det and self.oracle_options)
        chosen = greedy
        if not det:
            explore = torch.rand(batch, device=obs.device) < self.epsilon
            chosen = torch.where(explore, torch.randint(self.num_options, batch, device=obs.device), greedy)
            new_demo = torch.rand(batch, device=obs.device) < self.demo_ratio
            demo = torch.where(is_init, new_demo, td.get("demo_episode").reshape(batch).bool())
        option = torch.where(repick, chosen, prev)
        option = torch.where(demo, td.get("option").reshape(batch).long(), option)
        sub = td.get("sub_goals")
        td.set("option", option)
        td.set("option_start", repick)
        td.set("sub_goal", sub.gather(-2, option[..., None, None].expand(*batch, 1, sub.shape[-1])).squeeze(-2))
        with torch.no_grad():
            action = self.actor(td.select("observation", "sub_goal").copy()).get(self.action_key)
        if not det:
            fail = 1.0 - self.success_ema[goal].unsqueeze(-1)  # [*batch, 1]
            half = (self.high - self.low) / 2
            action = (action + torch.randn_like(action) * self.action_noise * fail * half).clamp(self.low, self.high)
            uniform = self.low + torch.rand_like(action) * (self.high - self.low)
            action = torch.where(torch.rand_like(fail) < self.random_action_prob * fail, uniform, action)
        td.set(self.action_key, action)
        td.set(("next", "prev_option"), option)
        td.set(("next", "demo_episode"), demo)
        return td


def goal_option_usage(td: TensorDictBase, alive: torch.Tensor, num_options: int) -> torch.Tensor:
    """``[n_goals, T, num_options]``: per goal, the fraction of its still-running evaluation episodes in which each option is active at each step."""
    goal = td.get("desired_goal")[:, 0].argmax(-1)
    onehot = F.one_hot(td.get("option").reshape(alive.shape), num_options).float() * alive.unsqueeze(-1)
    out = torch.zeros(num_options, alive.shape[1], num_options)
    for k in range(num_options):  # a handful of goals, once per evaluation
        sel = goal == k
        running = alive[sel].sum(0).clamp_min(1).unsqueeze(-1)
        out[k] = onehot[sel].sum(0) / running
    return out


def plot_goal_option_usage(usage: torch.Tensor, path, title: str = "option usage per goal") -> None:
    """One panel per goal: the stacked share of episodes in which each option (sub-goal) is active at each step (the paper's Figs. 6-7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_goals, t, n = usage.shape
    fig, axes = plt.subplots(1, n_goals, figsize=(3.2 * n_goals, 3.0), sharey=True, squeeze=False)
    for k, ax in enumerate(axes[0]):
        ax.stackplot(range(t), usage[k].T.numpy(), labels=[f"option {i}" for i in range(n)], alpha=0.85)
        ax.set_title(f"goal {k}")
        ax.set_xlabel("step")
        ax.set_ylim(0, 1)
    axes[0][0].set_ylabel("share of episodes")
    axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@register_agent("uof")
class UOFAgent(Agent):
    """UOF (module docstring) on a goal-conditioned env: the block-stacking model env, or the real task."""

    evaluation_files = ("option_usage.png",)

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        goal_key: str = "sub_goal",
        hidden_sizes: Sequence[int] = (256, 256, 256),
        lr: float = 1e-3,
        gamma: float = 0.98,
        tau: float = 0.1,
        batch_size: int = 128,
        updates_per_frame: float = 0.1,
        frames_per_batch: int = 400,
        buffer_size: int = 200_000,
        her_ratio: float = 0.8,
        her_per_option: bool = True,
        demo_ratio: float = 0.75,
        epsilon_decay_episodes: float = 30000.0,
        random_action_prob: float = 0.2,
        action_noise: float = 0.05,
        success_rate_ema: float = 0.05,
        low_target_range: Sequence[float] | None = (-25.0, 0.0),
        high_target_range: Sequence[float] | None = (-50.0, 0.0),
        fused_adam: bool = True,
    ):
        if goal_key != "sub_goal":
            raise ValueError(f"UOF's low level pursues the option's sub-goal: goal_key must be 'sub_goal', got {goal_key!r}")
        n_goals = env.observation_spec["desired_goal"].shape[-1]
        obs_dim = env.observation_spec["observation"].shape[-1]
        actor, qvalue = goal_networks(env, action_key, "sub_goal", hidden_sizes, obs_loc, obs_scale)
        scale = None if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32) + 0.01
        # the one-hot goal is not normalised (UOF): its normaliser is the identity
        high_net = TensorDictModule(GoalMLP(obs_dim, n_goals, 0, n_goals, list(hidden_sizes), "relu", obs_loc, scale, clip=3.0, last_layer_init=3e-3),
                                    in_keys=["observation", "desired_goal"], out_keys=["option_values"])
        self.high = DIOLLoss(high_net, num_options=n_goals, gamma=gamma, target_range=None if high_target_range is None else tuple(high_target_range))
        self.high.set_keys(reward="high_reward")
        self.low = TwinDDPGLoss(actor, qvalue, gamma=gamma, target_range=None if low_target_range is None else tuple(low_target_range))
        self.low.set_keys(action=action_key, reward=LOW_REWARD[1], done=LOW_DONE[1])
        self.loss = nn.ModuleDict({"high": self.high, "low": self.low})
        self.target_updaters = [SoftUpdate(self.high, tau=tau), SoftUpdate(self.low, tau=tau)]
        self.optimizer = adam(self.loss.parameters(), lr=lr, fused=fused_adam)
        _, low, high = action_box(env, action_key)
        self.policy = UOFPolicy(self.high, actor, low, high, n_goals, action_key, demo_ratio=demo_ratio, random_action_prob=random_action_prob,
                                action_noise=action_noise)
        self.num_options = n_goals
        self.action_key = action_key
        self.frames_per_batch = int(frames_per_batch)
        self.updates_per_frame = float(updates_per_frame)
        self.her_per_option = bool(her_per_option)
        self.epsilon_decay_episodes = float(epsilon_decay_episodes)
        self.success_rate_ema = float(success_rate_ema)
        self.replay_buffer = ReplayBuffers(
            high=ReplayBuffer(storage=LazyTensorStorage(int(buffer_size), device=device), batch_size=int(batch_size)),
            low=sub_goal_her_buffer(int(buffer_size), int(batch_size), her_ratio=her_ratio, device=device),
        )
        self.episodes = 0

    def env_transforms(self) -> list:
        return self.policy.make_transforms()

    def prepare(self, batch: TensorDictBase) -> TensorDictBase:
        """Annotate a collected ``[envs, time]`` batch: the low level's keys (:func:`~torchrl_offhrl.agents.her.prepare_low_level`) and the high level's reward."""
        prepare_low_level(batch, per_option=self.her_per_option)
        nxt = batch.get("next")
        reward = nxt.get("reward")
        own = (batch.get("option") == batch.get("desired_goal").argmax(-1)).reshape(reward.shape)
        penalized = nxt.get("penalized", torch.zeros_like(reward, dtype=torch.bool)).reshape(reward.shape)
        nxt.set("high_reward", torch.where(own | penalized, reward, torch.full_like(reward, -1.0)))
        return batch

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self.prepare(batch)
        flat = batch.reshape(-1)
        self.replay_buffer["high"].extend(flat.select(*_HIGH_KEYS))
        self.replay_buffer["low"].extend(flat.select(*low_level_keys(flat, self.action_key)))
        self.episodes += int(batch.get("is_init").sum())
        self.policy.epsilon = uof_epsilon(self.episodes, decay_episodes=self.epsilon_decay_episodes)
        metrics = MetricMeans()
        for _ in range(max(1, round(batch.numel() * self.updates_per_frame))):
            low = self.low(low_level_done(self.replay_buffer["low"].sample()))
            high = self.high(self.replay_buffer["high"].sample())
            self.optimizer.zero_grad()
            (low["loss_actor"] + low["loss_qvalue"] + high["loss_qvalue"]).backward()
            self.optimizer.step()
            for u in self.target_updaters:
                u.step()
            metrics.add({"loss_actor": low["loss_actor"], "loss_qvalue": low["loss_qvalue"], "loss_high_qvalue": high["loss_qvalue"],
                         "low_q_value": low["q_value"], "high_q_value": high["q_value"]})
        out = {**metrics.means(), "updates": metrics.count, "train/epsilon": self.policy.epsilon}
        out["train/option_start_rate"] = float(batch.get("option_start").float().mean())
        return out

    def evaluation_metrics(self, rollout, alive) -> dict:
        """Per-goal success of the evaluation episodes (env reward 0 at some step) updates the exploration's ``sr_g`` (UOF); plus the option shares."""
        goal = rollout.get("desired_goal")[:, 0].argmax(-1)
        success = G.success_by_goal(rollout.get(("next", "reward")).reshape(alive.shape), alive, goal, self.num_options)
        seen = ~success.isnan()
        ema = self.policy.success_ema
        ema[seen] = (1 - self.success_rate_ema) * ema[seen] + self.success_rate_ema * success[seen].to(ema)
        usage = F.one_hot(rollout.get("option").reshape(alive.shape), self.num_options).float()[alive].mean(0)
        return {"option_usage_mean": usage.tolist(), "exploration_success_ema": ema.tolist()}

    def save_evaluation(self, rollout, alive, run_dir: Path, title: str) -> None:
        usage = goal_option_usage(rollout, alive, self.num_options)
        torch.save(usage, Path(run_dir) / "option_usage.pt")
        plot_goal_option_usage(usage, Path(run_dir) / "option_usage.png", title=f"UOF option usage per goal, {title}")

    def state_dict(self) -> dict:
        return {**super().state_dict(), "target_updaters": [u.state_dict() for u in self.target_updaters], "episodes": self.episodes,
                "success_ema": self.policy.success_ema.clone()}

    def load_state_dict(self, state) -> None:
        super().load_state_dict(state)
        for u, s in zip(self.target_updaters, state["target_updaters"]):
            u.load_state_dict(s)
        self.episodes = int(state["episodes"])
        self.policy.success_ema.copy_(state["success_ema"])
        self.policy.epsilon = uof_epsilon(self.episodes, decay_episodes=self.epsilon_decay_episodes)

    def new_task(self) -> None:
        self.replay_buffer.empty()
