"""The offline training recipe, the same for every agent: ``train(cfg)``.

Driven by ``offhrl train`` and ``offhrl demo`` (``examples/offline_train.py``
writes the same steps out as a script):

1. config -> dataset (a file, a local Minari id, or a named level generated
   and cached on first use) -> cached dynamics ensemble and CVAE;
2. ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)`` with the
   paper's per-dataset pessimism (``configs/env/*.yaml``);
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

Nothing here names an algorithm.
"""
from __future__ import annotations

import json
import time
from collections.abc import Mapping

import torch
from torchrl.envs import RewardScaling, RewardSum

from ..agents import AGENTS, agent_defaults, goal_conditioned, make_agent, requires_goal
from ..blockstack import BLOCKSTACK_IDS
from ..blockstack import goals as G
from ..utils import atomic_write, to_plain
from .config import (
    acts_in_latent_space, config_fingerprint, default_run_dir, learns_from_dataset, model_config, model_env_config, resolve_dataset, resolve_reward_scale,
    transfer_config,
)
from .evaluation import Evaluator, GoalEvaluator
from .pipeline import fit_or_load_models, make_model_env, make_real_env
from .report import UNIT_LABELS, fmt_number, plot_curve, plot_goal_success, plot_training_metrics, plot_transfer, run_summary
from .rundir import RunDirectory
from .schema import validate_config
from .selection import PolicySelector
from .sources import dataset_batches, env_collector, model_env_metrics, online_metrics

TIMING_KEYS = ("frames_per_s", "updates_per_s", "update_time_s", "data_s", "models_s", "total_s")  # a run's summary: what it measured

__all__ = ["train"]

#: dataset agents (one gradient step per batch) log the mean of their metrics over this many updates
LOG_EVERY_UPDATES = 100


def train(cfg: Mapping, progress: bool = True) -> dict:
    """Run one recipe end to end; returns the summary also written to ``run_dir/summary.json``.

    The run directory is locked for the whole run: a second ``train`` on the
    same directory (another process, or this one) is refused with
    ``RuntimeError`` instead of interleaving its checkpoints and logs.
    """
    cfg = to_plain(cfg)
    validate_config(cfg)  # every bad value named before any data or model work
    t_start = time.time()
    run = RunDirectory(cfg.get("run_dir") or default_run_dir(cfg), config_fingerprint(cfg))
    with run.locked():  # refused here, a run leaves the directory alone: it belongs to the run holding the lock
        try:
            return _train(cfg, run, t_start, progress)
        except BaseException:
            run.remove_if_empty()  # a run that failed before writing anything (say, on a bad dataset) leaves no folder
            raise


def _train(cfg: dict, run: RunDirectory, t_start: float, progress: bool) -> dict:
    from tqdm.auto import tqdm

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
    stacking = env_cfg["env_id"] in BLOCKSTACK_IDS  # goal-conditioned: per-goal success, agents conditioned on the sub-goal
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
    bound = cfg.get("model_env", {}).get("latent_bound", 2.0)

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
                              task=None if tcfg is None else "forward", gamma=float(algo.get("gamma", 0.99)))
    if tcfg is not None:
        with torch.random.fork_rng():  # the offline phase of a transfer run is the offline run of the same seed, draw for draw
            if online_env is None:
                online_env = agent.attach(real_env(int(tcfg["num_envs"]), tcfg["task"]))
                add_reward_transforms(online_env)
            online_eval_env = agent.attach(real_env(episodes, tcfg["task"]))
        online_evaluator = Evaluator(online_eval_env, env_cfg["env_id"], episodes, int(cfg["eval"]["max_steps"]), seed=eval_seed, ref=ref,
                                     task=tcfg["task"])
    title = f"{env_cfg['env_id']}, {cfg['dataset']}"

    # 4. resume, log, train, evaluate, checkpoint
    run.data_hash = data.content_hash()  # a run never resumes on other data found at the same path
    run.unit = unit
    # offline policy selection: the policy a run returns is chosen from its evaluations without the real env; it needs the
    # model env's evaluation, so dataset agents, online and transfer runs, and block stacking return their last policy
    scfg = cfg.get("selection") or {}
    selectable = model_eval_env is not None and tcfg is None and not stacking
    run.selector = PolicySelector(scfg.get("criterion", "last") if selectable else "last", scfg.get("include_start", False))
    previous_summary = None
    if run.resume(agent, device) and (run.path / "summary.json").is_file():
        previous_summary = json.loads((run.path / "summary.json").read_text())
        (run.path / "summary.json").unlink()  # a run taken further is unfinished until its new summary: archives skip it meanwhile
    run.write_json("config.json", {**cfg, "resolved_pessimism": pess, "threshold": threshold, "resolved_reward_scale": pcfg["env"].get("reward_scale", 1.0),
                                   "model_dir": model_info["model_dir"], "data_hash": run.data_hash, "unit": unit})
    logger = run.logger(cfg.get("logger", {}).get("backend"), **cfg.get("logger", {}).get("kwargs", {}))

    def evaluate(ev: Evaluator, save_to=None, phase: str | None = None) -> dict:
        rec = {"frames": run.frames, "updates": run.updates, "step": run.step, "wall_s": round(time.time() - t_start, 1)}
        if phase is not None:
            rec["phase"] = phase
        rec.update(ev(agent, save_to=save_to, title=title))
        if phase in (None, "offline"):  # the offline phase's policies are the candidates of the selection
            run.selector.consider(rec, agent, run.step)
        return rec

    def train_phase(source, start: int, budget: int, every: int, ev: Evaluator, desc: str, batch_metrics, phase: str | None, final_dir) -> None:
        """Update on every batch of ``source`` until ``start + budget``; evaluate with ``ev`` every ``every`` steps after ``start``."""
        end = start + budget
        bar = tqdm(total=budget, initial=min(run.step - start, budget), desc=desc, disable=not progress, unit=unit[:-1])
        next_eval = start + ((run.step - start) // every + 1) * every
        pending, pending_n = {}, 0
        for batch in source:
            t0 = time.time()
            agent.set_progress((run.step - start) / budget)  # before this batch counts: schedules (e.g. anneal_lr) follow the phase's budget
            before = run.step
            run.frames += batch.numel()
            metrics = agent.update(batch)
            run.updates += int(metrics.pop("updates"))
            timing["update_time_s"] += time.time() - t0
            if batch_metrics is not None:
                metrics.update(batch_metrics(batch))
            for k, v in metrics.items():  # (sum, count) per key: some metrics come with some updates only (e.g. a delayed actor)
                total_k, n_k = pending.get(k, (0.0, 0))
                pending[k] = (total_k + v, n_k + 1)
            pending_n += 1
            if logger is not None and (not from_dataset or pending_n >= LOG_EVERY_UPDATES or run.step >= end):
                for k, (v, n) in pending.items():  # dataset agents: the mean over LOG_EVERY_UPDATES updates (their 0-dim tensors, read now)
                    logger.log_scalar(k, float(v) / n, step=run.step)
            if not from_dataset or pending_n >= LOG_EVERY_UPDATES:
                pending, pending_n = {}, 0
            bar.update(run.step - before)
            if run.step >= next_eval or run.step >= end:
                rec = evaluate(ev, save_to=final_dir if run.step >= end else None, phase=phase)
                run.records.append(rec)
                if logger is not None:
                    for k in ("return_mean", "normalized_d4rl", "model_return_mean", "model_real_gap", "success_rate"):
                        if rec.get(k) is not None:
                            logger.log_scalar(f"eval/{k}", rec[k], step=run.step)
                score = "" if rec["normalized_d4rl"] is None else f" (D4RL-normalised {rec['normalized_d4rl']:.1f})"
                if "success_per_goal" in rec:
                    score = f", success per goal {' '.join(f'{x:.2f}' for x in rec['success_per_goal'])}"
                bar.set_postfix(ret=f"{rec['return_mean']:.0f}", score=fmt_number(rec["normalized_d4rl"]))
                where = f"{env_cfg['env_id']}" + (f" ({rec['task']} task)" if "task" in rec else "")
                bar.write(f"[{run.step} {unit}] real {where} return {rec['return_mean']:.1f} ± {rec['return_std']:.1f}{score}")
                for snap in sorted(x for x in snapshots if x <= run.step and not (run.path / f"snapshot-{x}.pt").is_file()):
                    # a state kept for good (e.g. UOF's 20-epoch policy), at the first evaluation at or past it, before the checkpoint
                    # moves on (a run killed in between takes it again on resume)
                    with atomic_write(run.path / f"snapshot-{snap}.pt") as tmp:
                        torch.save({"agent": agent.state_dict(), "frames": run.frames, "updates": run.updates, "step": run.step, "record": rec}, tmp)
                run.checkpoint(agent)
                next_eval = start + ((run.step - start) // every + 1) * every
                if run.step >= end:
                    break
        bar.close()

    snapshots = {int(x) for x in cfg["train"].get("snapshot_frames") or []}
    every = int(cfg["eval"][f"every_{unit}"])
    if any(x % every for x in snapshots):
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: a snapshot is taken at an evaluation, so each must be a multiple of "
                         f"eval.every_{unit} ({every})")
    if any(x > int(cfg["train"][f"total_{unit}"]) for x in snapshots) and tcfg is None:
        raise ValueError(f"train.snapshot_frames {sorted(snapshots)}: past the budget train.total_{unit}={cfg['train'][f'total_{unit}']}")
    frames_at_start, updates_at_start = run.frames, run.updates
    timing = {"update_time_s": 0.0}
    t_train = time.time()
    phase_name = None if tcfg is None else "offline"
    switch = None
    if offline:  # the offline phase: on the model env, or on the dataset
        total, eval_every = int(cfg["train"][f"total_{unit}"]), int(cfg["eval"][f"every_{unit}"])
        done_offline = tcfg is not None and any(r.get("phase") == "online" for r in run.records)
        remaining = 0 if done_offline else max(total - run.step, 0)
        if env is not None:
            env.set_seed(cfg["seed"] + run.frames)
        if remaining > 0 and not run.records and cfg["eval"].get("at_start", True):
            # the untrained agent: the start of the learning curve (with the CVAE: about the decoder's mean action)
            run.records.append(evaluate(evaluator, phase=phase_name))
            run.checkpoint(agent)
        final_dir = run.path if tcfg is None else run.path / "offline"  # a transfer run's last files are its online phase's
        if remaining > 0:
            if from_dataset:  # the sampling continues from the run's restored RNG state
                source = dataset_batches(data, agent, remaining, device=device)
            else:
                source = env_collector(env, agent, remaining, frames_done=run.frames, device=device)
            train_phase(source, 0, total, eval_every, evaluator, f"{algo['name']} on {env_cfg['name']}" + (" (online)" if online else f"-{level}"),
                        None if from_dataset else online_metrics if online else model_env_metrics,
                        phase_name, final_dir)
            if not from_dataset:
                source.shutdown()
        elif not run.records:
            run.records.append(evaluate(evaluator, save_to=final_dir, phase=phase_name))
            run.checkpoint(agent)
    if tcfg is not None:  # the online phase: fine-tuning in the real env, on the new task
        switch = next((r["frames"] for r in run.records if r.get("phase") == "online"), None)
        if switch is None:  # the switch: the agent as it starts on the new task (after the offline phase's last evaluation, on the old task)
            switch = run.frames
            if offline:
                agent.new_task()
            run.records.append(evaluate(online_evaluator, phase="online"))
            run.checkpoint(agent)
        budget = int(tcfg["online_frames"])
        remaining = max(switch + budget - run.frames, 0)
        if remaining > 0:
            online_env.set_seed(cfg["seed"] + run.frames)
            # random actions only for a run from scratch: after the offline phase frames_done > 0, and the agent acts from the start
            source = env_collector(online_env, agent, remaining, frames_done=run.frames, device=device)
            train_phase(source, switch, budget, int(tcfg["eval_every_frames"]), online_evaluator,
                        f"{algo['name']} on {env_cfg['name']} ({tcfg['task']}, online)", online_metrics, "online", run.path)
            source.shutdown()
    last_evaluator = evaluator if tcfg is None else online_evaluator
    if not all((run.path / f).is_file() for f in agent.evaluation_files):
        rec = {**run.records[-1], **last_evaluator(agent, save_to=run.path, title=title)}  # the same policy again, for its files
        run.records[-1] = rec
        run.checkpoint(agent)
    selected = run.selector.selected
    if selected is not None and selected["agent"] is not None:  # the returned policy, with the evaluation it had when it was chosen
        with atomic_write(run.path / "selected.pt") as tmp:
            torch.save({"agent": selected["agent"], "step": selected["step"], "criterion": run.selector.criterion,
                        "record": run.records[selected["index"]]}, tmp)
    elapsed = time.time() - t_train
    train_time = timing["update_time_s"]

    # the report
    behaviour = data.return_stats()  # episodes cut short by the collection budget left out
    curve_title = f"{algo['name']} on {env_cfg['env_id']} ({cfg['dataset']})"
    if stacking:
        plot_goal_success([run.records], run.path / "success.png", label=algo["name"], title=curve_title, xlabel=UNIT_LABELS[unit])
    if tcfg is None:
        plot_curve([run.records], run.path / "learning_curve.png", label=algo["name"], title=curve_title, behaviour=behaviour["mean"], xlabel=UNIT_LABELS[unit])
    else:
        plot_transfer([run.records], run.path / "learning_curve.png", label=algo["name"], title=f"{curve_title}, then {tcfg['task']} online")
    summary = run_summary(
        cfg, data, behaviour, run.records, ref=ref, pessimism=pess, threshold=threshold, frames=run.frames, updates=run.updates,
        frames_per_s=(run.frames - frames_at_start) / elapsed if elapsed > 0 and run.frames > frames_at_start else None,
        updates_per_s=((run.updates - updates_at_start) / train_time) if train_time > 0 else None,
        timing={"update_time_s": train_time, "data_s": t_data, "models_s": t_models, "total_s": time.time() - t_start},
        models=model_info["model_dir"], run_dir=run.path, evaluation_files=agent.evaluation_files, unit=unit,
    )
    if run.frames == frames_at_start and run.updates == updates_at_start and previous_summary is not None:
        # a finished run called again (a results script rerun): nothing trained in this call, so its throughput and
        # timings stay those the run measured, instead of this call's few seconds of loading
        summary.update({k: previous_summary[k] for k in TIMING_KEYS if k in previous_summary})
    if stacking and data.metadata.get("goal_success"):  # the behaviour data's own per-goal success (its collection's horizon)
        summary["behaviour_success_per_goal"] = [data.metadata["goal_success"].get(str(k)) for k in range(n_goals)]
    if selected is not None:
        summary["selected"] = {**run.records[selected["index"]], "criterion": run.selector.criterion, "offline_score": selected["score"]}
    if tcfg is not None:
        summary["transfer"] = {**tcfg, "switch_frame": switch}
        summary["offline_final"] = next((r for r in reversed(run.records) if r.get("phase") == "offline"), None)
    run.write_json("summary.json", summary)
    plot_training_metrics(run.path / "logs", run.path / "training_metrics.png", xlabel=UNIT_LABELS["transfer" if tcfg else unit])
    for e in (eval_env, online_evaluator.env if online_evaluator else None, online_env):
        if e is not None:
            e.close()
    return summary
