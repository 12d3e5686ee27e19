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

import time
from collections.abc import Mapping

import torch
from torchrl.envs import RewardScaling, RewardSum

from ..agents import agent_defaults, make_agent
from ..utils import to_plain
from .config import (
    acts_in_latent_space, config_fingerprint, default_run_dir, learns_from_dataset, model_config, model_env_config, resolve_dataset, resolve_reward_scale,
)
from .evaluation import Evaluator
from .pipeline import fit_or_load_models, make_model_env, make_real_env
from .report import UNIT_LABELS, plot_curve, plot_training_metrics, run_summary
from .rundir import RunDirectory
from .schema import validate_config
from .sources import dataset_batches, model_env_collector, model_env_metrics

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

    # 1. data and models: one dataset for every training seed (its own seed is dataset_seed)
    data = resolve_dataset(cfg)
    level = data.metadata.get("level")
    t_data = time.time() - t_start
    pcfg = model_config(cfg)
    if from_dataset:
        ensemble = cvae = None
        model_info = {"model_dir": None}
    else:
        ensemble, cvae, model_info = fit_or_load_models(pcfg, data, progress=progress)
    t_models = time.time() - t_start - t_data
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg["torch_threads"]))
    torch.manual_seed(cfg["seed"])  # the agent's initial weights do not depend on whether the models were fitted or loaded

    # 2. the composed model env (no CVAE: the agent acts in real actions); none for an agent that learns from the dataset
    latent = acts_in_latent_space(cfg)
    episodes = int(cfg["eval"]["episodes"])
    stats = data.stats()
    env = model_eval_env = eval_env = None
    bound = cfg.get("model_env", {}).get("latent_bound", 2.0)
    if from_dataset:
        pess, threshold = None, None
        pcfg["env"] = {}
        if "reward_scale" in agent_defaults(algo["name"]):  # the rewards it learns from: a number, or a name resolved from the data
            algo = {**algo, "reward_scale": resolve_reward_scale(algo.get("reward_scale", 1.0), data, float(algo.get("gamma", 0.99)))}
            pcfg["env"]["reward_scale"] = algo["reward_scale"]
        eval_env = make_real_env(env_cfg["env_id"], None, num_envs=episodes)  # the env whose specs the agent is built for
    else:
        pcfg["env"], pess = model_env_config(cfg, level, data)
        env = make_model_env(pcfg, ensemble, cvae if latent else None, data, batch_size=int(cfg["collector"]["num_envs"]), latent=latent)
        threshold = env.base_env.threshold

    # 3. the agent, and the envs it acts in
    agent = make_agent(
        algo["name"], env if env is not None else eval_env, algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std,
        action_key="latent_action" if latent else "action", device=device,
    )
    if env is not None:
        agent.attach(env)
        env.append_transform(RewardSum())  # ("next", "episode_reward"): model returns in the logs
        if pcfg["env"].get("reward_scale", 1.0) != 1.0:  # what the agent learns from; logged and evaluated returns stay unscaled
            env.append_transform(RewardScaling(loc=0.0, scale=float(pcfg["env"]["reward_scale"])))
    if eval_env is None:  # built after the agent: its spec check draws from the RNG, and the agent's initial weights must not move
        eval_env = make_real_env(env_cfg["env_id"], cvae if latent else None, num_envs=episodes, latent_bound=bound)
    agent.attach(eval_env)
    if env is not None and cfg["eval"].get("model_env", True):  # the same evaluation in the model: the model-real gap
        model_eval_env = make_model_env(pcfg, ensemble, cvae if latent else None, data, batch_size=episodes, latent=latent, threshold=threshold,
                                         reset_states="initial")  # the real env's start states, whatever training uses
        agent.attach(model_eval_env)
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    evaluator = Evaluator(eval_env, env_cfg["env_id"], episodes, int(cfg["eval"]["max_steps"]), seed=int(cfg["seed"]) * 1000 + 7,
                          ref=ref if None not in ref else None, model_env=model_eval_env)
    title = f"{env_cfg['env_id']}, {cfg['dataset']}"

    # 4. resume, log, train, evaluate, checkpoint
    run.data_hash = data.content_hash()  # a run never resumes on other data found at the same path
    run.unit = unit
    run.resume(agent, device)
    run.write_json("config.json", {**cfg, "resolved_pessimism": pess, "threshold": threshold, "resolved_reward_scale": pcfg["env"].get("reward_scale", 1.0), "model_dir": model_info["model_dir"], "data_hash": run.data_hash, "unit": unit})
    logger = run.logger(cfg.get("logger", {}).get("backend"), **cfg.get("logger", {}).get("kwargs", {}))

    def evaluate(final: bool = False) -> dict:
        rec = {"frames": run.frames, "updates": run.updates, "step": run.step, "wall_s": round(time.time() - t_start, 1)}
        rec.update(evaluator(agent, save_to=run.path if final else None, title=title))
        return rec

    total, eval_every = int(cfg["train"][f"total_{unit}"]), int(cfg["eval"][f"every_{unit}"])
    remaining = max(total - run.step, 0)
    if env is not None:
        env.set_seed(cfg["seed"] + run.frames)
    t_train = time.time()
    frames_at_start, updates_at_start, train_time = run.frames, run.updates, 0.0
    if remaining > 0 and not run.records and cfg["eval"].get("at_start", True):
        # the untrained agent: the start of the learning curve (with the CVAE: about the decoder's mean action)
        run.records.append(evaluate())
        run.checkpoint(agent)
    if remaining > 0:
        if from_dataset:  # the sampling continues from the run's restored RNG state
            source = dataset_batches(data, agent, remaining, device=device)
        else:
            source = model_env_collector(env, agent, remaining, frames_done=run.frames, device=device)
        bar = tqdm(total=total, initial=run.step, desc=f"{algo['name']} on {env_cfg['name']}-{level}", disable=not progress, unit=unit[:-1])
        next_eval = (run.step // eval_every + 1) * eval_every
        pending, pending_n = {}, 0
        for batch in source:
            t0 = time.time()
            agent.set_progress(run.step / total)  # before this batch counts: schedules (e.g. anneal_lr) follow the budget
            before = run.step
            run.frames += batch.numel()
            metrics = agent.update(batch)
            run.updates += int(metrics.pop("updates"))
            train_time += time.time() - t0
            if env is not None:
                metrics.update(model_env_metrics(batch))
            for k, v in metrics.items():  # (sum, count) per key: some metrics come with some updates only (e.g. a delayed actor)
                total_k, n_k = pending.get(k, (0.0, 0))
                pending[k] = (total_k + v, n_k + 1)
            pending_n += 1
            if logger is not None and (env is not None or pending_n >= LOG_EVERY_UPDATES or run.step >= total):
                for k, (v, n) in pending.items():  # dataset agents: the mean over LOG_EVERY_UPDATES updates
                    logger.log_scalar(k, v / n, step=run.step)
            if env is not None or pending_n >= LOG_EVERY_UPDATES:
                pending, pending_n = {}, 0
            bar.update(run.step - before)
            if run.step >= next_eval or run.step >= total:
                rec = evaluate(final=run.step >= total)
                run.records.append(rec)
                if logger is not None:
                    for k in ("return_mean", "normalized_d4rl", "model_return_mean", "model_real_gap"):
                        if rec.get(k) is not None:
                            logger.log_scalar(f"eval/{k}", rec[k], step=run.step)
                bar.set_postfix(ret=f"{rec['return_mean']:.0f}", score=f"{rec['normalized_d4rl'] or 0:.1f}")
                bar.write(f"[{run.step} {unit}] real {env_cfg['env_id']} return {rec['return_mean']:.1f} ± {rec['return_std']:.1f} "
                          f"(D4RL-normalised {rec['normalized_d4rl'] or float('nan'):.1f})")
                run.checkpoint(agent)
                next_eval = (run.step // eval_every + 1) * eval_every
                if run.step >= total:
                    break
        bar.close()
        if not from_dataset:
            source.shutdown()
    elif not run.records:
        run.records.append(evaluate(final=True))
        run.checkpoint(agent)
    if not all((run.path / f).is_file() for f in agent.evaluation_files):
        run.records[-1] = evaluate(final=True)
        run.checkpoint(agent)
    elapsed = time.time() - t_train

    # the report
    behaviour = data.return_stats()  # episodes cut short by the collection budget left out
    plot_curve([run.records], run.path / "learning_curve.png", label=algo["name"], title=f"{algo['name']} on {env_cfg['env_id']} ({cfg['dataset']})",
               behaviour=behaviour["mean"], xlabel=UNIT_LABELS[unit])
    summary = run_summary(
        cfg, data, behaviour, run.records, ref=evaluator.ref, pessimism=pess, threshold=threshold, frames=run.frames, updates=run.updates,
        frames_per_s=(run.frames - frames_at_start) / elapsed if elapsed > 0 and run.frames > frames_at_start else None,
        updates_per_s=((run.updates - updates_at_start) / train_time) if train_time > 0 else None,
        timing={"update_time_s": train_time, "data_s": t_data, "models_s": t_models, "total_s": time.time() - t_start},
        models=model_info["model_dir"], run_dir=run.path, evaluation_files=agent.evaluation_files, unit=unit,
    )
    run.write_json("summary.json", summary)
    plot_training_metrics(run.path / "logs", run.path / "training_metrics.png", xlabel=UNIT_LABELS[unit])
    eval_env.close()
    return summary
