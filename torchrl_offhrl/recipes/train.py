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

How: :func:`~torchrl_offhrl.recipes.setting.build_setting` builds the
run's parts (data, models, agent, envs, evaluators) and its phases
(:mod:`~torchrl_offhrl.recipes.loop`: one offline phase, or the transfer
setting's offline and online phases); a
:class:`~torchrl_offhrl.recipes.loop.TrainingLoop` runs each phase; then
the returned policy (offline policy selection) and the report.

Nothing here names an algorithm.
"""
from __future__ import annotations

import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass

from ..utils import checksum_path, save_torch_file, to_plain
from .config import config_fingerprint, default_run_dir
from .loop import TrainingLoop
from .plots import plot_training_metrics
from .summary import run_summary
from .rundir import RunDirectory
from .runs import read_json
from .schema import RunConfig
from .selection import PolicySelector, data_return_cap
from .setting import build_setting

TIMING_KEYS = ("frames_per_s", "updates_per_s", "update_time_s", "data_s", "models_s", "total_s")  # a run's summary: what it measured

__all__ = ["PreparedRun", "run_directory", "train"]


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
