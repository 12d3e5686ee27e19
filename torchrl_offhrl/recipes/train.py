"""The offline training recipe, the same for every agent: ``train(cfg)``.

Driven by ``offhrl train`` and ``offhrl demo`` (``examples/offline_train.py``
and ``examples/offline_baseline.py`` run the same steps and the same loop as
scripts):

1. config -> dataset (a file, a local Minari id, or a named level generated
   and cached on first use) -> cached dynamics ensemble and CVAE;
2. ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)`` whose
   settings the offline rules compute from the data and the fitted models
   (:mod:`torchrl_offhrl.envs.rules`; printed as the calibration report;
   ``preset=paper``: the paper's per-dataset tables);
3. the agent registered under ``cfg.algo.name`` (:mod:`torchrl_offhrl.agents`)
   and a TorchRL collector on the model env;
4. ``agent.update(batch)`` on every batch; every ``eval.every_frames``
   frames a deterministic evaluation in the real env through the same
   decoder, logged, checkpointed atomically (rerunning resumes), and at the
   end the learning curve and the agent's own evaluation files.

Model-free offline agents (``data_source = "dataset"``: IQL, CQL, TD3+BC,
BC) skip steps 1's models and 2: they learn from minibatches of the dataset
itself, act in real actions, and their budget and evaluation period are
counted in gradient steps (``train.total_updates``, ``eval.every_updates``).
Their evaluation is the same: same real env, episodes and seeds.

How, in this module, in reading order: :func:`train` opens the run
directory, :meth:`PreparedRun.prepare` builds the run and resumes it, a
:class:`~torchrl_offhrl.recipes.loop.TrainingLoop` runs each phase,
:meth:`PreparedRun.finish` returns the policy (offline policy selection,
the guard) and writes the report. What a run is made of comes from
:func:`build_setting`: the config's *setting* (:func:`setting_of`) is one
of four, each a class with its own ``build``: :class:`ModelEnvSetting`
(the paper's: on the composed model env, the block-stacking tasks
included), :class:`DatasetSetting` (agents that learn from the dataset
itself), :class:`OnlineSetting` (the real env from scratch) and
:class:`TransferSetting` (offline, then online on a new task; or its
online-only baseline). :func:`build_setting` checks the config's
combination, loads what every setting starts from (:class:`Parts`: the
data and, where the setting uses them, the models) and hands it to the
setting, which builds the agent, its envs and evaluators and returns a
:class:`Setting`: the agent and its phases, plus what the report needs.
The loop does not know which setting it runs; a new setting is a new class
in :data:`SETTINGS`.

Nothing here names an algorithm.
"""
from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torchrl.envs import RewardScaling, RewardSum

from ..agents import AGENTS, agent_defaults, goal_conditioned, make_agent, requires_goal
from ..blockstack import goals as G
from ..registry import task_of
from ..utils import checksum_path, save_torch_file, to_plain
from .config import (RULE_KEYS, acts_in_latent_space, config_fingerprint, data_label, default_run_dir, latent_bound, learns_from_dataset, model_config,
                     model_env_batch, model_env_config, offline_rules_for, resolve_dataset, resolve_reward_scale, rules_not_used, transfer_config)
from .evaluation import Evaluator, GoalEvaluator
from .loop import OfflinePhase, OnlinePhase, Phase, TrainingLoop, dataset_batches, env_collector, model_env_metrics, online_metrics
from .pipeline import (DEFAULT_ORIGIN_SHARE, apply_latent_origin, fit_or_load_models, make_eval_model_env, make_model_env, make_real_env,
                       origin_share)
from .plots import UNIT_LABELS, plot_curve, plot_goal_success, plot_training_metrics, plot_transfer
from .rundir import RunDirectory
from .runs import read_json
from .schema import RunConfig, TransferConfig
from .selection import PolicySelector, data_return_cap
from .summary import run_summary

TIMING_KEYS = ("frames_per_s", "updates_per_s", "update_time_s", "data_s", "models_s", "total_s")  # a run's summary: what it measured

__all__ = [
    "DatasetSetting", "ModelEnvSetting", "ModelPart", "OnlineSetting", "Parts", "PreparedRun", "SETTINGS", "Setting", "TransferSetting", "build_setting",
    "eval_seed", "run_directory", "setting_of", "train",
]


def train(cfg: Mapping, progress: bool = True, on_record=None) -> dict:
    """Run one recipe end to end; returns the summary also written to ``run_dir/summary.json``.

    ``on_record``: called with each evaluation record as it is made (a Ray
    Tune trial reports them: :mod:`~torchrl_offhrl.recipes.tune`).

    The run directory is locked for the whole run: a second ``train`` on the
    same directory (another process, or this one) is refused with
    ``RuntimeError`` instead of interleaving its checkpoints and logs.
    """
    cfg = to_plain(cfg)
    rc = RunConfig.parse(cfg)  # the typed sections; every bad value named before any data or model work
    t_start = time.time()
    run = run_directory(cfg)
    with run.locked():  # refused here, a run leaves the directory alone: it belongs to the run holding the lock
        try:
            return _train(cfg, rc, run, t_start, progress, on_record)
        except BaseException:
            run.remove_if_empty()  # a run that failed before writing anything (say, on a bad dataset) leaves no folder
            raise


def run_directory(cfg: Mapping) -> RunDirectory:
    """The run directory of a validated config: ``run_dir``, else the default one of its algorithm, data and seed."""
    return RunDirectory(cfg.get("run_dir") or default_run_dir(cfg), config_fingerprint(cfg))


def _train(cfg: dict, rc: RunConfig, run: RunDirectory, t_start: float, progress: bool, on_record=None) -> dict:
    r = PreparedRun.prepare(cfg, run, t_start, progress, on_record, rc=rc)
    for phase in r.setting.phases:
        r.loop.run_phase(phase)
    return r.finish()


@dataclass
class PreparedRun:
    """One run between its preparation (setting built, checkpoint resumed, logger open) and its report (:meth:`finish`)."""

    cfg: dict
    run: RunDirectory
    setting: object
    loop: TrainingLoop
    t_start: float
    t_train: float
    frames_at_start: int
    updates_at_start: int
    previous_summary: dict | None

    @classmethod
    def prepare(cls, cfg: dict, run: RunDirectory, t_start: float, progress: bool, on_record=None, rc: RunConfig | None = None) -> PreparedRun:
        rc = RunConfig.parse(cfg) if rc is None else rc
        s = build_setting(cfg, run.path, t_start, progress, rc=rc)  # data, models, agent, envs, evaluators, phases
        cfg = s.cfg  # the config with what the setting resolved from the data and the models (resolved_model_env)
        agent, unit = s.agent, s.unit
        run.data_hash = s.data.content_hash()  # a run never resumes on other data found at the same path
        run.unit = unit
        criterion, guard = (rc.selection.criterion, rc.selection.guard) if s.selectable else ("last", False)
        if (criterion == "model_gain_lcb" or guard) and not rc.eval.at_start:
            warnings.warn(f"selection.criterion={criterion} / selection.guard={guard} compare the trained policies with the evaluation "
                          "at step 0, which eval.at_start=false skips: the last policy is returned, unguarded", stacklevel=2)
            criterion, guard = ("last" if criterion == "model_gain_lcb" else criterion), False
        cap = data_return_cap(s.data, rc.eval.max_steps) if rc.selection.return_cap == "data" else None
        run.selector = PolicySelector(criterion, rc.selection.include_start, guard=guard, return_cap=cap,
                                      prefer="start" if rc.selection.fallback == "start_unless_bc" else "bc")
        previous_summary = None
        resumed = run.resume(agent, s.device)
        if not resumed:  # a start from the dataset before training (e.g. MOReL's behaviour cloning); a resumed run has it in its weights
            pretrained = agent.pretrain(s.data, progress=progress)
            if pretrained:
                run.write_json("pretrain.json", pretrained)
        if resumed and (run.path / "summary.json").is_file():
            try:
                previous_summary = read_json(run.path / "summary.json")
            except ValueError as err:  # damaged: the run is taken further all the same, and writes it again
                warnings.warn(f"{err}; the previous summary is dropped", stacklevel=2)
            (run.path / "summary.json").unlink()  # a run taken further is unfinished until its new summary: archives skip it meanwhile
            checksum_path(run.path / "summary.json").unlink(missing_ok=True)
        if s.rules is not None:  # the calibration report: what the offline rules chose, and why (text, JSON, figure)
            run.write_json("calibration.json", s.rules.as_dict())
            s.rules.plot(run.path / "calibration.png")
            if progress:
                print(s.rules.summary() + f"\n  (figure: {run.path / 'calibration.png'})", flush=True)
        run.write_json("config.json", {**cfg, "resolved_pessimism": s.pessimism, "threshold": s.threshold, "resolved_reward_scale": s.reward_scale,
                                       "model_dir": s.model_info["model_dir"], "data_hash": run.data_hash, "unit": unit})
        logger = run.logger(rc.logger.backend, **rc.logger.kwargs)
        loop = TrainingLoop(run, agent, logger=logger, title=s.title, snapshots=s.snapshots, t_start=t_start, progress=progress, env_label=s.env_label,
                            on_record=on_record)
        return cls(cfg, run, s, loop, t_start, time.time(), run.frames, run.updates, previous_summary)

    def finish(self) -> dict:
        """The returned policy (``selected.pt``), the curves and the summary (``summary.json``, also returned)."""
        cfg, run, s, agent, unit = self.cfg, self.run, self.setting, self.setting.agent, self.setting.unit
        if not all((run.path / f).is_file() for f in agent.evaluation_files):
            rec = {**run.records[-1], **s.phases[-1].evaluator(agent, save_to=run.path, title=s.title)}  # the same policy again, for its files
            run.records[-1] = rec
            run.checkpoint(agent)
        selected = run.selector.selected
        cloned, fallback, fallback_error = None, None, None
        if run.selector.guard and s.fallback is not None and (run.selector.start or {}).get("agent") is not None:
            try:  # the percentile BC of the start's episodes, evaluated as the agent is (recipes.fallback)
                cloned, fallback = s.fallback()
            except (RuntimeError, ValueError) as err:  # the run's policies are kept whatever the BC does: the start alone
                fallback_error = f"the percentile BC could not be fitted or evaluated ({type(err).__name__}: {err}); the start is the only fallback"
                warnings.warn(fallback_error, stacklevel=2)
            else:
                run.write_json("fallback.json", fallback)  # its whole record, model episodes included (what the guard paired)
        verdict = run.selector.verdict(fallback)  # the guard: the start (or the BC) instead, when no member shows a gain over them
        if verdict is not None and verdict["fired"]:
            if verdict.get("against") == "bc":
                selected = {"index": None, "step": 0, "score": verdict["gain_lcb"], "agent": None, "bc": cloned.state_dict(), "record": fallback}
            else:
                start = run.selector.start
                selected = {"index": start["index"], "step": 0, "score": verdict["gain_lcb"], "agent": start["agent"]}
        if selected is not None and selected["agent"] is None and "bc" not in selected and verdict is not None:
            selected = {**selected, "agent": agent.state_dict()}  # the last policy, kept whole beside the guard's choice
        if selected is not None and "bc" in selected:  # a policy in real actions, not the agent: evaluation.load_run_agent reads it
            save_torch_file({"policy": "percentile_bc", "bc": selected["bc"], "step": 0, "criterion": run.selector.criterion,
                             "record": selected["record"]}, run.path / "selected.pt")
        elif selected is not None and selected["agent"] is not None:  # the returned policy, with the evaluation it had when it was chosen
            save_torch_file({"agent": selected["agent"], "step": selected["step"], "criterion": run.selector.criterion,
                             "record": run.records[selected["index"]]}, run.path / "selected.pt")
        elapsed, train_time = time.time() - self.t_train, self.loop.timing["update_time_s"]

        # the report
        behaviour = s.data.return_stats()  # episodes cut short by the collection budget left out
        s.plot_curves(run.records, run.path, behaviour["mean"])
        summary = run_summary(
            cfg, s.data, behaviour, run.records, ref=s.ref, pessimism=s.pessimism, threshold=s.threshold, frames=run.frames, updates=run.updates,
            frames_per_s=(run.frames - self.frames_at_start) / elapsed if elapsed > 0 and run.frames > self.frames_at_start else None,
            updates_per_s=((run.updates - self.updates_at_start) / train_time) if train_time > 0 else None,
            timing={"update_time_s": train_time, "data_s": s.t_data, "models_s": s.t_models, "total_s": time.time() - self.t_start},
            models=s.model_info["model_dir"], run_dir=run.path, evaluation_files=agent.evaluation_files, unit=unit,
        )
        if run.frames == self.frames_at_start and run.updates == self.updates_at_start and self.previous_summary is not None:
            # a finished run called again (a results script rerun): nothing trained in this call, so its throughput and
            # timings stay those the run measured, instead of this call's few seconds of loading
            summary.update({k: self.previous_summary[k] for k in TIMING_KEYS if k in self.previous_summary})
        if selected is not None:
            chosen = selected["record"] if "bc" in selected else run.records[selected["index"]]
            summary["selected"] = {**chosen, "criterion": run.selector.criterion, "offline_score": selected["score"],
                                   **({"frames": 0, "policy": "percentile_bc"} if "bc" in selected else {})}
            for k in ("model_episode_returns", "model_episode_members"):
                summary["selected"].pop(k, None)
        if fallback is not None:  # what the percentile BC scored, whether or not it was returned
            summary["fallback"] = {k: v for k, v in fallback.items() if k not in ("model_episode_returns", "model_episode_members")}
        if verdict is not None and fallback_error is not None:
            verdict = {**verdict, "reason": f"{verdict['reason']}; {fallback_error}"}
        if verdict is not None:
            summary["guard"] = {**verdict, "returned": ("bc" if verdict.get("against") == "bc" else "start") if verdict["fired"] else "trained",
                                "candidate_step": None if run.selector.selected is None else run.selector.selected["step"]}
        elif s.selectable:  # a model-env run with the guard off (selection.guard=false): say so, and what the user gets instead
            summary["guard"] = {"fired": None, "gain_lcb": None, "returned": "trained",
                                "reason": "selection.guard=false: the selected policy is returned unguarded"}
        summary.update(s.summary_extras(run.records))
        if s.rules is not None:
            summary["calibration"] = s.rules.as_dict()
        run.write_json("summary.json", summary)
        plot_training_metrics(run.path / "logs", run.path / "training_metrics.png", xlabel=s.xlabel)
        s.close()
        return summary


# ---- what a run is made of, built from its config: one builder per setting (data, models, agent, envs, phases) -----------

def eval_seed(seed: int) -> int:
    """The seed of a run's real-env evaluations, from the run's ``seed`` (every evaluation of a run starts from it)."""
    return int(seed) * 1000 + 7


@dataclass
class Setting:
    """What a setting built for a run (:func:`build_setting`): the loop runs ``phases`` with ``agent``; the report reads
    the rest, and what the run started from (its config, data, models, timings) through :attr:`parts`."""

    parts: Parts                # what the setting was built from, with the env's settings it resolved (Parts.with_model_env)
    agent: object
    phases: list[Phase]
    unit: str = "frames"        # "frames" (collected) or "updates" (gradient steps: the dataset agents)
    selectable: bool = False    # whether the offline policy selection may pick another policy than the last
    pessimism: dict | None = None
    threshold: float | None = None
    closers: list = field(default_factory=list)  # the real envs to close at the end
    eval_env_for: Callable | None = None  # copies -> one real env holding `copies` evaluations' envs, the agent's transforms appended
    fallback: Callable | None = None  # () -> (ClonedPolicy, its evaluation record): the guard's percentile BC (recipes.fallback)

    # what the run started from, read from its parts
    cfg = property(lambda self: self.parts.cfg, doc="The run's config, with what the setting resolved (``resolved_model_env``).")
    data = property(lambda self: self.parts.data)
    snapshots = property(lambda self: self.parts.snapshots, doc="The steps whose agent state is kept for good (train.snapshot_frames).")
    transfer = property(lambda self: self.parts.rc.transfer, doc="The transfer settings, or None.")
    stacking = property(lambda self: self.parts.stacking, doc="A goal-conditioned block-stacking task.")
    n_goals = property(lambda self: self.parts.n_goals)
    model_info = property(lambda self: self.parts.model_info)
    ref = property(lambda self: self.parts.ref)
    t_data = property(lambda self: self.parts.t_data)
    t_models = property(lambda self: self.parts.t_models)
    device = property(lambda self: self.parts.device)
    env_label = property(lambda self: self.parts.env_id, doc="The real env's id, in progress lines.")
    title = property(lambda self: f"{self.parts.env_id}, {self.parts.cfg['dataset']}", doc="The evaluation plots' title.")
    reward_scale = property(lambda self: self.parts.pcfg["env"].get("reward_scale", 1.0), doc="The reward scale the agent learns with.")

    @property
    def rules(self):
        """The OfflineRules that set the P-MDP (envs.rules; None: none ran): the run's calibration report."""
        return self.parts.rules

    def close(self) -> None:
        for e in self.closers:
            if e is not None:
                e.close()

    @property
    def xlabel(self) -> str:
        """The x-axis of the run's curves and logs."""
        return UNIT_LABELS["transfer" if self.transfer else self.unit]

    def plot_curves(self, records: list[dict], folder: Path, behaviour_mean: float | None) -> None:
        """The run's learning curve (``learning_curve.png``: both phases of a transfer run) and, on a goal-conditioned task, ``success.png``."""
        algo = self.cfg["algo"]["name"]
        title = f"{algo} on {self.cfg['env']['env_id']} ({self.cfg['dataset']})"
        if self.stacking:
            plot_goal_success([records], folder / "success.png", label=algo, title=title, xlabel=UNIT_LABELS[self.unit])
        if self.transfer is None:
            plot_curve([records], folder / "learning_curve.png", label=algo, title=title, behaviour=behaviour_mean, xlabel=UNIT_LABELS[self.unit])
        else:
            plot_transfer([records], folder / "learning_curve.png", label=algo, title=f"{title}, then {self.transfer.task} online")

    def summary_extras(self, records: list[dict]) -> dict:
        """What the setting adds to a run's summary: the data's per-goal success (block stacking), the switch (transfer)."""
        out = {}
        if self.stacking and self.data.metadata.get("goal_success"):  # the behaviour data's own per-goal success (its collection's horizon)
            out["behaviour_success_per_goal"] = [self.data.metadata["goal_success"].get(str(k)) for k in range(self.n_goals)]
        if self.transfer is not None:
            out["transfer"] = {**asdict(self.transfer), "switch_frame": self.phases[-1].start}
            out["offline_final"] = next((r for r in reversed(records) if r.get("phase") == "offline"), None)
        return out


def snapshot_steps(rc: RunConfig, unit: str) -> set[int]:
    """``train.snapshot_frames`` as a set, checked: each falls on an evaluation and (one-phase runs) within the budget."""
    snapshots = set(rc.train.snapshot_frames)
    every, total = rc.eval.every(unit), rc.train.total(unit)
    if any(x % every for x in snapshots):
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: a snapshot is taken at an evaluation, so each must be a multiple of "
                         f"eval.every_{unit} ({every})")
    if any(x > total for x in snapshots) and rc.transfer is None:
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: past the budget train.total_{unit}={total}")
    return snapshots


def _check_combination(cfg: dict) -> None:
    """Refuse the config combinations no setting defines, each with what to do."""
    algo, env_id = cfg["algo"]["name"], cfg["env"]["env_id"]
    from_dataset, tcfg, online = learns_from_dataset(cfg), transfer_config(cfg), bool(cfg["train"].get("online", False))
    ablations = [k for k, v in cfg.get("ablation", {}).items() if v]
    stacking = task_of(env_id).goal_conditioned
    if from_dataset and ablations:
        raise ValueError(f"algo={algo} learns from the dataset itself, with no model env or CVAE: the ablations "
                         f"{ablations} do not apply to it; leave them false")
    if from_dataset and tcfg is not None:
        raise ValueError(f"algo={algo} learns from the dataset itself; the transfer setting fine-tunes online an agent trained "
                         "on the model env (moc, ppo, sac, ...): leave transfer.task null")
    if stacking and not goal_conditioned(algo):
        raise ValueError(f"algo={algo} is not goal-conditioned; on {env_id} use one of {sorted(n for n in AGENTS if goal_conditioned(n))}")
    if not stacking and requires_goal(algo):
        raise ValueError(f"algo={algo} acts on the goal-conditioned block-stacking tasks only (env=blockstack2|blockstack3), not {env_id}")
    if stacking and tcfg is not None:
        raise ValueError(f"the transfer setting is defined for the locomotion tasks (run backwards), not {env_id}: leave transfer.task null")
    if online and (from_dataset or tcfg is not None):
        raise ValueError(f"train.online=true trains an agent that collects (moc, ppo, sac, uof, ...) in the real env from scratch; "
                         f"{'algo=' + algo + ' learns from the dataset itself' if from_dataset else 'the transfer setting has its own online phase'}: "
                         "leave train.online false")
    if online and ablations:
        raise ValueError(f"train.online=true trains in the real env in real actions, with no models or CVAE: the ablations "
                         f"{ablations} do not apply to it; leave them false")


@dataclass
class Parts:
    """What every setting starts from (:func:`build_setting`): the config, the task, the data, the models it uses, timings."""

    cfg: dict
    rc: RunConfig               # the typed sections of cfg (train, eval, selection, collector, transfer, logger)
    run_path: Path
    device: torch.device
    stacking: bool              # a goal-conditioned block-stacking task (task_of(env_id).goal_conditioned)
    data: object
    n_goals: int
    level: str | None
    pcfg: dict                  # model_config(cfg); with the env's settings under "env" once resolved (with_model_env)
    ensemble: object
    cvae: object
    model_info: dict
    t_data: float
    t_models: float
    snapshots: set[int]
    rules: object = None        # the OfflineRules of the model env, once a setting computed them
    progress: bool = True       # progress bars on long work (fits)
    fallback: object = None     # the guard's percentile BC, fitted and evaluated on demand (Setting.fallback)

    def with_model_env(self, env: dict, rules=None, resolved: dict | None = None) -> Parts:
        """New parts whose env settings (``pcfg["env"]``: the reward scale, the model env's horizon, threshold, ...) are
        ``env``, computed by a setting from these parts; ``rules``: the offline rules that resolved them; ``resolved``: what
        the run's ``config.json`` keeps of them (``cfg["resolved_model_env"]``, which
        :func:`~torchrl_offhrl.recipes.config.latent_bound` reads). These parts are left as they are."""
        cfg = self.cfg if resolved is None else {**self.cfg, "resolved_model_env": resolved}
        return replace(self, cfg=cfg, pcfg={**self.pcfg, "env": env}, rules=self.rules if rules is None else rules)

    @property
    def env_id(self) -> str:
        return self.cfg["env"]["env_id"]

    @property
    def episodes(self) -> int:
        return self.rc.eval.episodes

    @property
    def ref(self) -> tuple | None:
        ref = (self.data.metadata.get("ref_min_return"), self.data.metadata.get("ref_max_return"))
        return ref if None not in ref else None

    @property
    def eval_seed(self) -> int:
        return eval_seed(self.rc.seed)

    def make_agent(self, env, algo: dict | None = None, latent: bool = True):
        """The config's agent, built for ``env``'s specs, acting in latent actions (``latent``) or real ones."""
        stats = self.data.stats()
        return make_agent((algo or self.cfg["algo"])["name"], env, algo or self.cfg["algo"], obs_loc=stats.obs_mean, obs_scale=stats.obs_std,
                          action_key="latent_action" if latent else "action", device=self.device, goal_key="sub_goal" if self.stacking else None)

    def eval_real_env(self, cvae, copies: int = 1):
        """The real env of the evaluations, through ``cvae``'s decoder (or in real actions): per goal ``episodes`` copies on a stacking task.

        ``copies``: that many evaluations' envs in one env, one block after the other (a seeds' batch evaluates its
        runs together: :class:`~torchrl_offhrl.recipes.evaluation.SeedsEvaluation`)."""
        bound = latent_bound(self.cfg)
        if not self.stacking:
            return make_real_env(self.env_id, cvae, num_envs=self.episodes * copies, latent_bound=bound)
        goals = [k for _ in range(copies) for k in range(self.n_goals) for _ in range(self.episodes)]
        return make_real_env(self.env_id, cvae, num_envs=len(goals), latent_bound=bound, goals=goals, max_episode_steps=self.rc.eval.max_steps)

    def add_reward_transforms(self, env):
        """Returns in the logs (``RewardSum``) and the reward scale the agent learns with; logged and evaluated returns stay unscaled."""
        env.append_transform(RewardSum())
        if self.pcfg["env"].get("reward_scale", 1.0) != 1.0:
            env.append_transform(RewardScaling(loc=0.0, scale=float(self.pcfg["env"]["reward_scale"])))
        return env

    def evaluator(self, eval_env, model_eval_env=None, task: str | None = None, algo: dict | None = None):
        """The evaluation of ``eval_env``: per goal on a stacking task (:class:`GoalEvaluator`), else returns (:class:`Evaluator`)."""
        ev = self.rc.eval
        if self.stacking:
            return GoalEvaluator(eval_env, self.env_id, self.episodes, self.n_goals, int(self.pcfg["env"].get("horizon", 25)),
                                 ev.max_steps, seed=self.eval_seed, model_env=model_eval_env)
        return Evaluator(eval_env, self.env_id, self.episodes, ev.max_steps, seed=self.eval_seed, ref=self.ref, model_env=model_eval_env,
                         task=task, gamma=float((algo or self.cfg["algo"]).get("gamma", 0.99)), sampled=ev.sampled)

    def data_name(self) -> str:
        """The data by name for a progress bar: a file's (or Minari id's) own name, else the generated level (``hopper-medium``)."""
        label = data_label({"dataset": self.cfg["dataset"], "level": self.level, "env_id": self.env_id})
        return Path(label).name if "/" in label else label

    def offline_phase(self, evaluator, batches, unit: str, batch_metrics, seed_env, online: bool = False, transfer: bool = False) -> OfflinePhase:
        """The phase from step 0 (the run's only one, or a transfer run's offline phase, ``"offline"``)."""
        cfg, rc = self.cfg, self.rc
        return OfflinePhase(
            name="offline" if transfer else None, evaluator=evaluator, total=rc.train.total(unit), every=rc.eval.every(unit), batches=batches,
            desc=f"{cfg['algo']['name']} on " + (f"{cfg['env']['name']} (online)" if online else self.data_name()),
            final_dir=Path(self.run_path) / "offline" if transfer else Path(self.run_path),  # a transfer run's last files are its online phase's
            batch_metrics=batch_metrics, seed_env=seed_env, seed=rc.seed, at_start=rc.eval.at_start,
            done_when="online" if transfer else None,
        )

    def setting(self, agent, phases: list[Phase], unit: str = "frames", selectable: bool = False,
                pessimism: dict | None = None, threshold: float | None = None, closers: tuple = (), eval_env_for: Callable | None = None) -> Setting:
        """The :class:`Setting` of these parts, with what the setting built."""
        return Setting(parts=self, agent=agent, phases=phases, unit=unit, selectable=selectable, pessimism=pessimism, threshold=threshold,
                       closers=list(closers), eval_env_for=eval_env_for, fallback=self.fallback if selectable else None)


def _fallback(p: Parts, evaluator, threshold: float) -> Callable:
    """``() -> (policy, record)``: the guard's percentile BC of the episodes the latent origin clones (all of them with
    ``latent_origin: behaviour``, the default share otherwise), fitted or loaded and evaluated as ``evaluator`` evaluates the agent."""
    from ..models import ClonedPolicy
    from .fallback import evaluate_fallback, fit_or_load_bc

    share = origin_share(p.pcfg["env"]) or DEFAULT_ORIGIN_SHARE

    def run():
        bc = fit_or_load_bc(p.pcfg, p.data, p.model_info.get("model_dir"), share, p.rc.seed, progress=p.progress)
        record = evaluate_fallback(bc, evaluator.env_id, evaluator.episodes, evaluator.max_steps, evaluator.seed, p.pcfg, p.ensemble, p.data, threshold,
                                   model_episodes=evaluator.model_env.batch_size.numel(), ref=evaluator.ref, gamma=evaluator.gamma,
                                   device=p.device)  # only built with a model eval env (ModelEnvSetting)
        return ClonedPolicy(bc), {**record, "share": share}

    return run


class ModelEnvSetting:
    """The paper's setting: the agent trains on ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)`` (real actions
    with ``ablation.no_cvae``), evaluated in the real env and in the model; its returned policy is chosen offline
    (``selection.criterion``). The block-stacking tasks too: goals and rewards on the predicted states, per-goal evaluation."""

    unit = "frames"

    @staticmethod
    def applies(cfg: dict) -> bool:
        return True  # what is left when no other setting applies

    @staticmethod
    def needs_models(cfg: dict) -> bool:
        return True

    @staticmethod
    def model_part(p: Parts, transfer: bool = False) -> ModelPart:
        """The model env's agent and its offline phase, on new parts with the model env's settings resolved."""
        cfg, latent = p.cfg, acts_in_latent_space(p.cfg)
        cvae = p.cvae if latent else None
        # the offline rules: every `auto` setting of the P-MDP from the data and the fitted models (envs.rules; the calibration report)
        rules = offline_rules_for(cfg, p.data, p.ensemble, cvae)
        env_settings, pess = model_env_config(cfg, p.level, p.data, rules=rules)
        not_used = rules_not_used(cfg, env_settings, rules) if rules is not None else None
        if not_used:  # the calibration report says which of the rules' values this run sets otherwise (none: nothing added)
            rules.info["not_used"] = not_used
        # the run's config.json keeps what the rules resolved
        p = p.with_model_env(env_settings, rules=rules, resolved={k: env_settings[k] for k in RULE_KEYS if k in env_settings})
        if cvae is not None:  # model_env.latent_origin: where an agent's latent 0 decodes to (best: the best episodes' action at each state)
            _, origin_info = apply_latent_origin(p.pcfg, p.data, cvae, p.model_info.get("model_dir"), progress=p.progress)
            if origin_info is not None and rules is not None:  # in the calibration report
                rules.info["latent_origin"] = origin_info
        env = make_model_env(p.pcfg, p.ensemble, cvae, p.data, batch_size=model_env_batch(cfg), latent=latent)
        threshold = env.base_env.threshold
        agent = p.make_agent(env, latent=latent)
        p.add_reward_transforms(agent.attach(env))
        agent.use_dataset(p.data, float(p.pcfg["env"].get("reward_scale", 1.0)))  # the rewards as the env's transforms scale them
        eval_env = agent.attach(p.eval_real_env(cvae))  # after the agent: its spec check draws from the RNG, and the agent's initial weights must not move
        model_eval_env = None
        if p.rc.eval.model_env:  # the same evaluation in the model: the model-real gap
            # the real env's start states, whatever training uses; every member rolls out the same number of episodes (the LCB over members)
            # episodes as long as the real env's (eval.max_steps), whatever the training horizon: the model's verdict on a policy is
            # only as long as its episodes, and the guard compares whole episodes (recipes.selection)
            model_eval_env = agent.attach(make_eval_model_env(p.pcfg, p.ensemble, cvae, p.data, p.rc.eval.model_episodes or p.episodes,
                                                              p.rc.eval.max_steps, threshold, latent=latent))
        evaluator = p.evaluator(eval_env, model_eval_env, task="forward" if transfer else None)
        if model_eval_env is not None and not p.stacking and not transfer and p.rc.selection.fallback != "start":
            p = replace(p, fallback=_fallback(p, evaluator, threshold))
        phase = p.offline_phase(evaluator, lambda remaining, frames_done: env_collector(env, agent, remaining, frames_done=frames_done, device=p.device),
                                "frames", model_env_metrics, env, transfer=transfer)
        # offline policy selection needs the model env's evaluation; block stacking returns its last policy
        return ModelPart(p, agent, phase, eval_env, pess, threshold, model_eval_env is not None and not p.stacking)

    def build(self, p: Parts) -> Setting:
        m = self.model_part(p)
        cvae = m.parts.cvae if acts_in_latent_space(m.parts.cfg) else None
        return m.parts.setting(m.agent, [m.phase], selectable=m.selectable, pessimism=m.pessimism, threshold=m.threshold, closers=(m.eval_env,),
                               eval_env_for=lambda copies: m.agent.attach(m.parts.eval_real_env(cvae, copies)))


@dataclass
class ModelPart:
    """What :meth:`ModelEnvSetting.model_part` builds: the parts with the model env's settings resolved, the agent, its
    offline phase, its real evaluation env, the resolved pessimism and threshold, and whether the returned policy may be
    selected offline (the model env's evaluation ran)."""

    parts: Parts
    agent: object
    phase: OfflinePhase
    eval_env: object
    pessimism: dict | None
    threshold: float
    selectable: bool


class DatasetSetting:
    """Model-free offline agents (``data_source = "dataset"``: IQL, CQL, TD3+BC, BC): minibatches of the dataset, real
    actions, budget and evaluation period in gradient steps; no models, no model env; the last policy is returned."""

    unit = "updates"

    @staticmethod
    def applies(cfg: dict) -> bool:
        return learns_from_dataset(cfg)

    @staticmethod
    def needs_models(cfg: dict) -> bool:
        return False

    def build(self, p: Parts) -> Setting:
        algo, env_settings = p.cfg["algo"], {}
        if "reward_scale" in agent_defaults(algo["name"]):  # the rewards it learns from: a number, or a name resolved from the data
            algo = {**algo, "reward_scale": resolve_reward_scale(algo.get("reward_scale", 1.0), p.data, float(algo.get("gamma", 0.99)))}
            env_settings["reward_scale"] = algo["reward_scale"]
        p = p.with_model_env(env_settings)
        eval_env = p.eval_real_env(None)  # the env whose specs the agent is built for
        agent = p.make_agent(eval_env, algo, latent=acts_in_latent_space(p.cfg))
        agent.attach(eval_env)
        # the sampling continues from the run's restored RNG state
        phase = p.offline_phase(p.evaluator(eval_env, algo=algo), lambda remaining, frames_done: dataset_batches(p.data, agent, remaining, device=p.device),
                                self.unit, None, None)
        return p.setting(agent, [phase], unit=self.unit, closers=(eval_env,),
                         eval_env_for=lambda copies: agent.attach(p.eval_real_env(None, copies)))


class OnlineSetting:
    """``train.online``: the agent trains in the real env from scratch, in real actions (no models, no CVAE); the dataset
    gives only the input statistics and the reward scale. The paper's route to its block-stacking data."""

    unit = "frames"

    @staticmethod
    def applies(cfg: dict) -> bool:
        return bool(cfg["train"].get("online", False))

    @staticmethod
    def needs_models(cfg: dict) -> bool:
        return False

    def build(self, p: Parts) -> Setting:
        cfg = p.cfg
        settings, _ = model_env_config(cfg, p.level, p.data)  # the reward scale the agent learns with (resolved as on the model env) and the horizon
        env_settings = {k: settings[k] for k in ("reward_scale", "horizon") if k in settings}
        if p.stacking:  # goals drawn by the env at each reset
            env_settings.setdefault("horizon", 25)
        p = p.with_model_env(env_settings)
        env = make_real_env(p.env_id, None, num_envs=p.rc.collector.num_envs,
                            **({"max_episode_steps": int(p.pcfg["env"]["horizon"])} if p.stacking else {}))
        agent = p.make_agent(env, latent=False)
        p.add_reward_transforms(agent.attach(env))
        eval_env = agent.attach(p.eval_real_env(None))
        phase = p.offline_phase(p.evaluator(eval_env), lambda remaining, frames_done: env_collector(env, agent, remaining, frames_done=frames_done, device=p.device),
                                "frames", online_metrics, env, online=True)
        return p.setting(agent, [phase], closers=(eval_env,))


class TransferSetting:
    """The paper's second setting (``transfer.task``): the model env's offline phase, then online fine-tuning in the real
    env on a new task, one x-axis of frames; ``transfer.from_scratch``: the online phase alone (the baseline)."""

    unit = "frames"

    @staticmethod
    def applies(cfg: dict) -> bool:
        return transfer_config(cfg) is not None

    @staticmethod
    def needs_models(cfg: dict) -> bool:
        tcfg = transfer_config(cfg)  # from scratch without the decoder: no model
        return not tcfg["from_scratch"] or (acts_in_latent_space(cfg) and tcfg["decoder"] == "keep")

    def build(self, p: Parts) -> Setting:
        cfg, tcfg = p.cfg, p.rc.transfer
        latent = acts_in_latent_space(cfg)
        keep_decoder = latent and tcfg.decoder == "keep"

        def real_env(num_envs: int):  # the real env of the online phase, on the new task, in the action space the agent acts in
            # (`p`: the parts as resolved below, whose config holds the latent box the offline rules chose)
            return make_real_env(p.env_id, p.cvae if keep_decoder else None, num_envs=num_envs, latent_bound=latent_bound(p.cfg), task=tcfg.task,
                                 discard_decoder=latent and not keep_decoder)

        phases, eval_env, pess, threshold = [], None, None, None
        if not tcfg.from_scratch:
            m = ModelEnvSetting.model_part(p, transfer=True)
            p, agent, eval_env, pess, threshold = m.parts, m.agent, m.eval_env, m.pessimism, m.threshold
            phases.append(m.phase)
            with torch.random.fork_rng():  # the offline phase of a transfer run is the offline run of the same seed, draw for draw
                online_env = p.add_reward_transforms(agent.attach(real_env(tcfg.num_envs)))
                online_eval_env = agent.attach(real_env(p.episodes))
        else:  # the agent is built for the real env it trains in; no P-MDP
            p = p.with_model_env(model_env_config(cfg, p.level, p.data)[0])  # the reward scale it learns with
            online_env = real_env(tcfg.num_envs)
            agent = p.make_agent(online_env, latent=latent)
            p.add_reward_transforms(agent.attach(online_env))
            with torch.random.fork_rng():
                online_eval_env = agent.attach(real_env(p.episodes))
        online_evaluator = Evaluator(online_eval_env, p.env_id, p.episodes, p.rc.eval.max_steps, seed=p.eval_seed, ref=p.ref, task=tcfg.task)
        # random actions only for a run from scratch: after the offline phase frames_done > 0, and the agent acts from the start
        phases.append(OnlinePhase(
            name="online", evaluator=online_evaluator, total=tcfg.online_frames, every=tcfg.eval_every_frames,
            batches=lambda remaining, frames_done: env_collector(online_env, agent, remaining, frames_done=frames_done, device=p.device),
            desc=f"{cfg['algo']['name']} on {cfg['env']['name']} ({tcfg.task}, online)", final_dir=Path(p.run_path),
            batch_metrics=online_metrics, seed_env=online_env, seed=p.rc.seed, selects=False, new_task=not tcfg.from_scratch,
        ))
        return p.setting(agent, phases, pessimism=pess, threshold=threshold, closers=(eval_env, online_eval_env, online_env))


#: the settings a run can be, the first whose ``applies(cfg)`` holds is built (the model env's is the default)
SETTINGS = (DatasetSetting(), TransferSetting(), OnlineSetting(), ModelEnvSetting())


def setting_of(cfg: dict):
    """The setting of a config (after refusing the combinations none defines)."""
    _check_combination(cfg)
    return next(s for s in SETTINGS if s.applies(cfg))


def build_setting(cfg: dict, run_path: Path, t_start: float, progress: bool = True, rc: RunConfig | None = None) -> Setting:
    """The :class:`Setting` of a config: data, models, agent, envs, evaluators and phases; files of the last
    evaluation go to ``run_path``. ``t_start``: the run's start (the data and model timings). ``rc``: the config's
    typed sections when the caller parsed them already (:meth:`RunConfig.parse`, which validates ``cfg``)."""
    rc = RunConfig.parse(cfg) if rc is None else rc
    kind = setting_of(cfg)
    torch.manual_seed(rc.seed)
    snapshots = snapshot_steps(rc, kind.unit)  # a bad value named before any data or model work
    data = resolve_dataset(cfg)  # one dataset for every training seed (its own seed is dataset_seed)
    stacking = task_of(cfg["env"]["env_id"]).goal_conditioned
    n_goals = G.n_goals(G.check_blocks(G.blocks_for_obs_dim(data.observation_dim))) if stacking else 0
    t_data = time.time() - t_start
    pcfg = model_config(cfg)
    ensemble = cvae = None
    model_info = {"model_dir": None}
    if kind.needs_models(cfg):
        ensemble, cvae, model_info = fit_or_load_models(pcfg, data, progress=progress)  # at fit_threads threads
    t_models = time.time() - t_start - t_data
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg["torch_threads"]))
    torch.manual_seed(rc.seed)  # the agent's initial weights do not depend on whether the models were fitted or loaded
    parts = Parts(cfg=cfg, rc=rc, run_path=Path(run_path), device=torch.device(cfg.get("device", "cpu")), stacking=stacking, data=data, n_goals=n_goals,
                  level=data.metadata.get("level"), pcfg=pcfg, ensemble=ensemble, cvae=cvae, model_info=model_info, t_data=t_data, t_models=t_models,
                  snapshots=snapshots, progress=progress)
    return kind.build(parts)  # the setting keeps the parts it resolved (Setting.parts)
