"""What a training run is made of, built from its config: the data, the models, the agent, the envs and the phases.

:func:`build_setting` is where the settings differ (the loop in
:mod:`~torchrl_offhrl.recipes.loop` does not): offline on the composed model
env, agents that learn from the dataset itself, online training in the real
env, the transfer setting (offline, then online on a new task) and the
goal-conditioned block-stacking tasks (their per-goal evaluator). It checks
that the config's combination is one of them, loads or generates the data,
fits or loads the models, builds the agent and the envs it acts in, and
returns a :class:`Setting`: the agent and its :class:`~torchrl_offhrl.recipes.loop.Phase`
list, plus what the report needs.
"""
from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torchrl.envs import RewardScaling, RewardSum

from ..agents import AGENTS, agent_defaults, goal_conditioned, make_agent, requires_goal
from ..blockstack import goals as G
from ..registry import task_of
from .config import acts_in_latent_space, latent_bound, learns_from_dataset, model_config, model_env_config, resolve_dataset, resolve_reward_scale, transfer_config
from .evaluation import Evaluator, GoalEvaluator
from .loop import OfflinePhase, OnlinePhase, Phase
from .pipeline import fit_or_load_models, make_model_env, make_real_env
from .plots import UNIT_LABELS, plot_curve, plot_goal_success, plot_transfer
from .sources import dataset_batches, env_collector, model_env_metrics, online_metrics

__all__ = ["Setting", "build_setting"]


@dataclass
class Setting:
    """A run's parts (:func:`build_setting`): the loop runs ``phases`` with ``agent``; the report reads the rest."""

    cfg: dict
    snapshots: set[int]         # the steps whose agent state is kept for good (train.snapshot_frames)
    data: object
    agent: object
    phases: list[Phase]
    unit: str                   # "frames" (collected) or "updates" (gradient steps: the dataset agents)
    title: str                  # the evaluation plots' title
    env_label: str              # the real env's id, in progress lines
    selectable: bool            # whether the offline policy selection may pick another policy than the last
    tcfg: dict | None           # the transfer settings, or None
    stacking: bool              # a goal-conditioned block-stacking task
    n_goals: int
    pessimism: dict | None
    threshold: float | None
    reward_scale: float
    model_info: dict
    ref: tuple | None
    t_data: float
    t_models: float
    device: torch.device
    closers: list = field(default_factory=list)  # the real envs to close at the end

    def close(self) -> None:
        for e in self.closers:
            if e is not None:
                e.close()

    @property
    def xlabel(self) -> str:
        """The x-axis of the run's curves and logs."""
        return UNIT_LABELS["transfer" if self.tcfg else self.unit]

    def plot_curves(self, records: list[dict], folder: Path, behaviour_mean: float | None) -> None:
        """The run's learning curve (``learning_curve.png``: both phases of a transfer run) and, on a goal-conditioned task, ``success.png``."""
        algo = self.cfg["algo"]["name"]
        title = f"{algo} on {self.cfg['env']['env_id']} ({self.cfg['dataset']})"
        if self.stacking:
            plot_goal_success([records], folder / "success.png", label=algo, title=title, xlabel=UNIT_LABELS[self.unit])
        if self.tcfg is None:
            plot_curve([records], folder / "learning_curve.png", label=algo, title=title, behaviour=behaviour_mean, xlabel=UNIT_LABELS[self.unit])
        else:
            plot_transfer([records], folder / "learning_curve.png", label=algo, title=f"{title}, then {self.tcfg['task']} online")

    def summary_extras(self, records: list[dict]) -> dict:
        """What the setting adds to a run's summary: the data's per-goal success (block stacking), the switch (transfer)."""
        out = {}
        if self.stacking and self.data.metadata.get("goal_success"):  # the behaviour data's own per-goal success (its collection's horizon)
            out["behaviour_success_per_goal"] = [self.data.metadata["goal_success"].get(str(k)) for k in range(self.n_goals)]
        if self.tcfg is not None:
            out["transfer"] = {**self.tcfg, "switch_frame": self.phases[-1].start}
            out["offline_final"] = next((r for r in reversed(records) if r.get("phase") == "offline"), None)
        return out


def snapshot_steps(cfg: Mapping, unit: str, tcfg: dict | None) -> set[int]:
    """``train.snapshot_frames`` as a set, checked: each falls on an evaluation and (one-phase runs) within the budget."""
    snapshots = {int(x) for x in cfg["train"].get("snapshot_frames") or []}
    every = int(cfg["eval"][f"every_{unit}"])
    if any(x % every for x in snapshots):
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: a snapshot is taken at an evaluation, so each must be a multiple of "
                         f"eval.every_{unit} ({every})")
    if any(x > int(cfg["train"][f"total_{unit}"]) for x in snapshots) and tcfg is None:
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: past the budget train.total_{unit}={cfg['train'][f'total_{unit}']}")
    return snapshots


def build_setting(cfg: dict, run_path: Path, t_start: float, progress: bool = True) -> Setting:
    """The :class:`Setting` of a validated config: data, models, agent, envs, evaluators and phases; files of the last
    evaluation go to ``run_path``. ``t_start``: the run's start (the data and model timings)."""
    algo, env_cfg = cfg["algo"], cfg["env"]
    torch.manual_seed(cfg["seed"])
    device = torch.device(cfg.get("device", "cpu"))
    from_dataset = learns_from_dataset(cfg)  # model-free offline: no models, no model env
    unit = "updates" if from_dataset else "frames"  # what the budget and the evaluation period count
    if from_dataset and any(cfg.get("ablation", {}).values()):
        raise ValueError(f"algo={algo['name']} learns from the dataset itself, with no model env or CVAE: the ablations "
                         f"{[k for k, v in cfg['ablation'].items() if v]} do not apply to it; leave them false")
    tcfg = transfer_config(cfg)  # None: offline training only
    if from_dataset and tcfg is not None:
        raise ValueError(f"algo={algo['name']} learns from the dataset itself; the transfer setting fine-tunes online an agent trained "
                         "on the model env (moc, ppo, sac, ...): leave transfer.task null")
    stacking = task_of(env_cfg["env_id"]).goal_conditioned  # goal-conditioned: per-goal success, agents conditioned on the sub-goal
    if stacking and not goal_conditioned(algo["name"]):
        raise ValueError(f"algo={algo['name']} is not goal-conditioned; on {env_cfg['env_id']} use one of "
                         f"{sorted(n for n in AGENTS if goal_conditioned(n))}")
    if not stacking and requires_goal(algo["name"]):
        raise ValueError(f"algo={algo['name']} acts on the goal-conditioned block-stacking tasks only (env=blockstack2|blockstack3), "
                         f"not {env_cfg['env_id']}")
    if stacking and tcfg is not None:
        raise ValueError(f"the transfer setting is defined for the locomotion tasks (run backwards), not {env_cfg['env_id']}: leave transfer.task null")
    online = bool(cfg["train"].get("online", False))  # the agent trains in the real env from scratch: no models, real actions
    if online and (from_dataset or tcfg is not None):
        raise ValueError(f"train.online=true trains an agent that collects (moc, ppo, sac, uof, ...) in the real env from scratch; "
                         f"{'algo=' + algo['name'] + ' learns from the dataset itself' if from_dataset else 'the transfer setting has its own online phase'}: "
                         "leave train.online false")
    if online and any(cfg.get("ablation", {}).values()):
        raise ValueError(f"train.online=true trains in the real env in real actions, with no models or CVAE: the ablations "
                         f"{[k for k, v in cfg['ablation'].items() if v]} do not apply to it; leave them false")
    offline = tcfg is None or not tcfg["from_scratch"]  # from scratch: the online phase only (the transfer setting's baseline)
    snapshots = snapshot_steps(cfg, unit, tcfg)  # a bad value named before any data or model work
    latent = acts_in_latent_space(cfg) and not online
    keep_decoder = latent and tcfg is not None and tcfg["decoder"] == "keep"

    # 1. data and models: one dataset for every training seed (its own seed is dataset_seed)
    data = resolve_dataset(cfg)
    n_goals = G.n_goals(G.check_blocks(G.blocks_for_obs_dim(data.observation_dim))) if stacking else 0
    level = data.metadata.get("level")
    t_data = time.time() - t_start
    pcfg = model_config(cfg)
    if from_dataset or online or not (offline or keep_decoder):  # a from-scratch run without the decoder needs no model
        ensemble = cvae = None
        model_info = {"model_dir": None}
    else:
        ensemble, cvae, model_info = fit_or_load_models(pcfg, data, progress=progress)
    t_models = time.time() - t_start - t_data
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg["torch_threads"]))
    torch.manual_seed(cfg["seed"])  # the agent's initial weights do not depend on whether the models were fitted or loaded

    # 2. the composed model env (no CVAE: the agent acts in real actions); none for an agent that learns from the dataset
    episodes = int(cfg["eval"]["episodes"])
    stats = data.stats()
    env = model_eval_env = eval_env = online_env = None
    bound = latent_bound(cfg)

    def eval_real_env(with_cvae):  # the evaluation env: per goal `episodes` copies on a goal-conditioned task
        if not stacking:
            return make_real_env(env_cfg["env_id"], with_cvae, num_envs=episodes, latent_bound=bound)
        goals = [k for k in range(n_goals) for _ in range(episodes)]
        return make_real_env(env_cfg["env_id"], with_cvae, num_envs=len(goals), latent_bound=bound, goals=goals,
                             max_episode_steps=int(cfg["eval"]["max_steps"]))

    def real_env(num_envs: int, task: str):  # the real env of the online phase, in the action space the agent acts in
        return make_real_env(env_cfg["env_id"], cvae if keep_decoder else None, num_envs=num_envs, latent_bound=bound, task=task,
                             discard_decoder=latent and not keep_decoder)

    def add_reward_transforms(e):
        e.append_transform(RewardSum())  # ("next", "episode_reward"): returns in the logs
        if pcfg["env"].get("reward_scale", 1.0) != 1.0:  # what the agent learns from; logged and evaluated returns stay unscaled
            e.append_transform(RewardScaling(loc=0.0, scale=float(pcfg["env"]["reward_scale"])))

    pess = threshold = None
    if from_dataset:
        pcfg["env"] = {}
        if "reward_scale" in agent_defaults(algo["name"]):  # the rewards it learns from: a number, or a name resolved from the data
            algo = {**algo, "reward_scale": resolve_reward_scale(algo.get("reward_scale", 1.0), data, float(algo.get("gamma", 0.99)))}
            pcfg["env"]["reward_scale"] = algo["reward_scale"]
        eval_env = eval_real_env(None)  # the env whose specs the agent is built for
    elif online:  # the real env in real actions, as many copies as collector.num_envs; goals drawn by the env at each reset
        settings, _ = model_env_config(cfg, level, data)  # the reward scale the agent learns with (resolved as on the model env) and the horizon
        pcfg["env"] = {k: settings[k] for k in ("reward_scale", "horizon") if k in settings}
        if stacking:
            pcfg["env"].setdefault("horizon", 25)
        env = make_real_env(env_cfg["env_id"], None, num_envs=int(cfg["collector"]["num_envs"]),
                            **({"max_episode_steps": int(pcfg["env"]["horizon"])} if stacking else {}))
    else:
        pcfg["env"], pess = model_env_config(cfg, level, data)
        if offline:
            env = make_model_env(pcfg, ensemble, cvae if latent else None, data, batch_size=int(cfg["collector"]["num_envs"]), latent=latent)
            threshold = env.base_env.threshold
        else:  # from scratch: the agent is built for the real env it trains in; no P-MDP
            pess = None
            online_env = real_env(int(tcfg["num_envs"]), tcfg["task"])

    # 3. the agent, and the envs it acts in
    agent = make_agent(
        algo["name"], next(e for e in (env, online_env, eval_env) if e is not None), algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std,
        action_key="latent_action" if latent else "action", device=device, goal_key="sub_goal" if stacking else None,
    )
    for e in (env, online_env):
        if e is not None:
            agent.attach(e)
            add_reward_transforms(e)
    if eval_env is None and offline:  # built after the agent: its spec check draws from the RNG, and the agent's initial weights must not move
        eval_env = eval_real_env(cvae if latent else None)
    if eval_env is not None:
        agent.attach(eval_env)
    if env is not None and not online and cfg["eval"].get("model_env", True):  # the same evaluation in the model: the model-real gap
        # the real env's start states, whatever training uses; every member rolls out the same number of episodes (the LCB over members)
        model_eval_env = make_model_env(pcfg, ensemble, cvae if latent else None, data, batch_size=int(cfg["eval"].get("model_episodes") or episodes),
                                         latent=latent, threshold=threshold, reset_states="initial", member_draw="cyclic")
        agent.attach(model_eval_env)
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    ref = ref if None not in ref else None
    eval_seed = int(cfg["seed"]) * 1000 + 7
    evaluator = online_evaluator = None
    if eval_env is not None and stacking:
        evaluator = GoalEvaluator(eval_env, env_cfg["env_id"], episodes, n_goals, int(pcfg["env"].get("horizon", 25)), int(cfg["eval"]["max_steps"]),
                                  seed=eval_seed, model_env=model_eval_env)
    elif eval_env is not None:
        evaluator = Evaluator(eval_env, env_cfg["env_id"], episodes, int(cfg["eval"]["max_steps"]), seed=eval_seed, ref=ref, model_env=model_eval_env,
                              task=None if tcfg is None else "forward", gamma=float(algo.get("gamma", 0.99)),
                              sampled=bool(cfg["eval"].get("sampled", False)))
    if tcfg is not None:
        with torch.random.fork_rng():  # the offline phase of a transfer run is the offline run of the same seed, draw for draw
            if online_env is None:
                online_env = agent.attach(real_env(int(tcfg["num_envs"]), tcfg["task"]))
                add_reward_transforms(online_env)
            online_eval_env = agent.attach(real_env(episodes, tcfg["task"]))
        online_evaluator = Evaluator(online_eval_env, env_cfg["env_id"], episodes, int(cfg["eval"]["max_steps"]), seed=eval_seed, ref=ref,
                                     task=tcfg["task"])
    title = f"{env_cfg['env_id']}, {cfg['dataset']}"

    phases: list[Phase] = []
    if offline:  # the offline phase: on the model env, or on the dataset
        if from_dataset:  # the sampling continues from the run's restored RNG state
            def batches(remaining, frames_done):
                return dataset_batches(data, agent, remaining, device=device)
        else:
            def batches(remaining, frames_done, env=env):
                return env_collector(env, agent, remaining, frames_done=frames_done, device=device)
        phases.append(OfflinePhase(
            name=None if tcfg is None else "offline", evaluator=evaluator, total=int(cfg["train"][f"total_{unit}"]),
            every=int(cfg["eval"][f"every_{unit}"]), batches=batches,
            desc=f"{algo['name']} on {env_cfg['name']}" + (" (online)" if online else f"-{level}"),
            final_dir=Path(run_path) if tcfg is None else Path(run_path) / "offline",  # a transfer run's last files are its online phase's
            batch_metrics=None if from_dataset else online_metrics if online else model_env_metrics,
            seed_env=env, seed=int(cfg["seed"]), at_start=bool(cfg["eval"].get("at_start", True)),
            done_when=None if tcfg is None else "online",
        ))
    if tcfg is not None:  # the online phase: fine-tuning in the real env, on the new task
        # random actions only for a run from scratch: after the offline phase frames_done > 0, and the agent acts from the start
        phases.append(OnlinePhase(
            name="online", evaluator=online_evaluator, total=int(tcfg["online_frames"]), every=int(tcfg["eval_every_frames"]),
            batches=lambda remaining, frames_done: env_collector(online_env, agent, remaining, frames_done=frames_done, device=device),
            desc=f"{algo['name']} on {env_cfg['name']} ({tcfg['task']}, online)", final_dir=Path(run_path),
            batch_metrics=online_metrics, seed_env=online_env, seed=int(cfg["seed"]), selects=False, new_task=offline,
        ))
    # offline policy selection: the policy a run returns is chosen from its evaluations without the real env; it needs the
    # model env's evaluation, so dataset agents, online and transfer runs, and block stacking return their last policy
    return Setting(
        cfg=cfg, snapshots=snapshots, data=data, agent=agent, phases=phases, unit=unit, title=title, env_label=env_cfg["env_id"],
        selectable=model_eval_env is not None and tcfg is None and not stacking, tcfg=tcfg, stacking=stacking, n_goals=n_goals,
        pessimism=pess, threshold=threshold, reward_scale=pcfg["env"].get("reward_scale", 1.0), model_info=model_info, ref=ref,
        t_data=t_data, t_models=t_models, device=device,
        closers=[eval_env, online_evaluator.env if online_evaluator else None, online_env],
    )
