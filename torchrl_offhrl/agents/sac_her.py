"""SAC + HER on a goal-conditioned task (the paper's flat block-stacking baseline): TorchRL's ``SACLoss`` on the low-level goal.

As the paper ran it: Stable-Baselines3's SAC and HER defaults (networks
[256, 256] ReLU, two critics, lr 3e-4, buffer 1e6, 100 random steps first,
batch 256, tau 0.005, gamma 0.99, one gradient step per step, automatic
entropy with target ``-dim(A)``; HER 'future' with 4 sampled goals per
transition, i.e. a relabelled share of 0.8), acting in the goal-conditioned
CVAE's latent space with the low-level goal (``sub_goal``: the env's
:class:`~torchrl_offhrl.envs.SubGoalTracker` follows the goal's abstract
demonstration, as the data were collected) as its goal. Relabelling and
rewards as UOF's low level (:mod:`~torchrl_offhrl.agents.her`): the reward
is 0 where the sub-goal is met at s', else -1, and the episode's end for
HER segments (``her_per_option=True`` relabels within option segments as
UOF does).

``terminal_on_success`` (True: this project's first version, as UOF's low
level) stops the critic's bootstrap where the sub-goal is met; False (the
default): only the model env's pessimistic terminations do, as in
Stable-Baselines3, whose goal envs end at their time limit only. With the bootstrap stopped at the
goal, SAC's entropy bonus (``-alpha log pi`` in every target) can make each
step worth more than the -1 reward costs, and reaching the goal, which ends
that stream, the worst thing to do: measured in
``docs/results/blockstack/sac_her_notes.md`` (True: success 1.0 / 1.0 / 0
fell to 0 / 0 / 0 within 4,800 frames; False: kept).
"""
from __future__ import annotations

from collections.abc import Sequence

from .her import LOW_DONE, LOW_REWARD, low_level_done, low_level_keys, prepare_low_level, sub_goal_her_buffer
from .registry import register_agent
from .sac import SACAgent, make_sac_loss, sac_optimizer
from .uof import goal_networks

__all__ = ["SACHERAgent"]


@register_agent("sac_her")
class SACHERAgent(SACAgent):
    """SAC conditioned on ``goal_key`` with hindsight relabelling of it (module docstring); otherwise :class:`SACAgent`'s loop."""

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        goal_key: str = "sub_goal",
        hidden_sizes: Sequence[int] = (256, 256),
        lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
        batch_size: int = 256,
        buffer_size: int = 1_000_000,
        init_random_frames: int = 100,
        utd_ratio: float = 1.0,
        frames_per_batch: int = 400,
        her_ratio: float = 0.8,
        her_per_option: bool = False,
        terminal_on_success: bool = False,
        fused_adam: bool = True,
        **loss_kwargs,
    ):
        if goal_key != "sub_goal":
            raise ValueError(f"SAC + HER relabels the low-level goal: goal_key must be 'sub_goal', got {goal_key!r}")
        self.policy, qvalue = goal_networks(env, action_key, goal_key, hidden_sizes, obs_loc, obs_scale, clip=None, last_layer_init=None,
                                            stochastic_actor=True)
        self.loss, self.target_updater = make_sac_loss(self.policy, qvalue, env.full_action_spec_unbatched[action_key], gamma=gamma, tau=tau,
                                                       action_key=action_key, **loss_kwargs)  # SACLoss's alpha_init, ... (SACAgent)
        self.loss.set_keys(reward=LOW_REWARD[1], done=LOW_DONE[1], terminated=LOW_DONE[1])
        self.optimizer = sac_optimizer(self.loss, lr, fused_adam)
        self.action_key = action_key
        self.frames_per_batch = int(frames_per_batch)
        self.init_random_frames = int(init_random_frames)
        self.utd_ratio = float(utd_ratio)
        self.her_per_option = bool(her_per_option)
        self.terminal_on_success = bool(terminal_on_success)
        self.replay_buffer = sub_goal_her_buffer(int(buffer_size), int(batch_size), her_ratio=her_ratio, device=device)
        self.frames = 0

    def update(self, batch):
        prepare_low_level(batch, per_option=self.her_per_option)
        flat = batch.reshape(-1)
        self.replay_buffer.extend(flat.select(*low_level_keys(flat, self.action_key)))
        return self.gradient_steps(batch.numel(), lambda: low_level_done(self.replay_buffer.sample(), on_success=self.terminal_on_success))
