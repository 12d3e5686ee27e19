"""Offline training on the pessimistic model env, for any registered agent, read top to bottom.

    python examples/offline_train.py algo=moc env=hopper dataset=medium
    python examples/offline_train.py algo=ppo env=hopper dataset=/data/hopper_medium.hdf5
    python examples/offline_train.py algo=sac env=halfcheetah dataset=medium-expert seed=1
    python examples/offline_train.py algo=moc ablation.no_cvae=true      # the paper's ablations
    python examples/offline_train.py algo=moc train.total_frames=200000 eval.every_frames=20000

config -> data -> models -> composed env -> agent -> collector -> update -> evaluate -> log / checkpoint.
Every algorithm trains on the same TransformedEnv(PessimisticModelEnv, LatentActionTransform);
only the `algo` config group changes (configs/algo/*.yaml, one agent file each in
torchrl_offhrl/agents/). Outputs go to outputs/runs/<algo>-<env>-<dataset>-seed<seed>/ (CSV
logs, evals.json, checkpoint.pt, learning_curve.png, the agent's own plots, summary.json);
running the same command again resumes from the checkpoint. `offhrl train` runs the same
recipe (torchrl_offhrl.recipes.train.train); aggregate seeds with `offhrl aggregate`.
"""
import time

import hydra
import torch
from omegaconf import DictConfig
from torchrl.envs import RewardScaling, RewardSum
from tqdm.auto import tqdm

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.recipes.config import (
    algo_label, config_fingerprint, default_run_dir, learns_from_dataset, model_config, model_env_config, offline_rules_for,
    resolve_dataset,
)
from torchrl_offhrl.recipes.evaluation import Evaluator
from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env, make_real_env
from torchrl_offhrl.recipes.report import format_summary, plot_curve, run_summary
from torchrl_offhrl.recipes.rundir import RunDirectory
from torchrl_offhrl.recipes.sources import env_collector, model_env_metrics
from torchrl_offhrl.utils import to_plain


@hydra.main(config_path="../configs", config_name="offline_train", version_base=None)
def main(cfg: DictConfig) -> None:
    # config
    cfg = to_plain(cfg)
    if learns_from_dataset(cfg):  # this script is the model-env loop; iql / cql / td3bc / bc learn from the dataset itself
        raise SystemExit(f"algo={algo_label(cfg['algo'])} learns from the dataset, not from the model env: run "
                         f"`offhrl train algo={cfg['algo']['name']} ...` (the same overrides), or examples/offline_baseline.py")
    t_start = time.time()
    algo, env_cfg = cfg["algo"], cfg["env"]
    run = RunDirectory(cfg.get("run_dir") or default_run_dir(cfg), config_fingerprint(cfg))
    device = torch.device(cfg["device"])
    torch.manual_seed(cfg["seed"])

    # data: a level name (generated and cached), an HDF5 file or a local Minari id
    data = resolve_dataset(cfg)
    t_data = time.time() - t_start

    # models: the dynamics ensemble and the CVAE, fitted once per dataset and cached
    mcfg = model_config(cfg)
    ensemble, cvae, model_info = fit_or_load_models(mcfg, data)
    t_models = time.time() - t_start - t_data
    if cfg["torch_threads"]:
        torch.set_num_threads(int(cfg["torch_threads"]))
    torch.manual_seed(cfg["seed"])

    # the composed env: TransformedEnv(PessimisticModelEnv, LatentActionTransform), its `auto` settings (threshold, penalty,
    # horizon, start states, latent box) from the offline rules: the data and the fitted models only (the calibration report)
    latent = not cfg["ablation"]["no_cvae"]
    rules = offline_rules_for(cfg, data, ensemble, cvae if latent else None)
    if rules is not None:
        print(rules.summary())
    mcfg["env"], pessimism = model_env_config(cfg, data.metadata.get("level"), data, rules=rules)
    env = make_model_env(mcfg, ensemble, cvae if latent else None, data, batch_size=cfg["collector"]["num_envs"], latent=latent)

    # the agent (configs/algo/<name>.yaml) and the transforms its policy needs on every env it acts in
    stats = data.stats()
    agent = make_agent(algo["name"], env, algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std,
                       action_key="latent_action" if latent else "action", device=device)
    agent.attach(env)
    env.append_transform(RewardSum())
    if mcfg["env"]["reward_scale"] != 1.0:  # what the agent learns from; logged and evaluated returns stay unscaled
        env.append_transform(RewardScaling(loc=0.0, scale=mcfg["env"]["reward_scale"]))

    # evaluation: deterministic, in the real env, through the same decoder
    eval_env = make_real_env(env_cfg["env_id"], cvae if latent else None, num_envs=cfg["eval"]["episodes"],
                             latent_bound=mcfg["env"].get("latent_bound", 2.0))
    agent.attach(eval_env)
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    evaluator = Evaluator(eval_env, env_cfg["env_id"], cfg["eval"]["episodes"], cfg["eval"]["max_steps"],
                          seed=cfg["seed"] * 1000 + 7, ref=None if None in ref else ref)

    def evaluate(final=False):
        rec = {"frames": run.frames, "updates": run.updates, "wall_s": round(time.time() - t_start, 1)}
        return {**rec, **evaluator(agent, save_to=run.path if final else None, title=f"{env_cfg['env_id']}, {cfg['dataset']}")}

    # checkpoint and logs: rerunning the command resumes
    run.resume(agent, device)
    run.write_json("config.json", {**cfg, "resolved_pessimism": pessimism, "threshold": env.base_env.threshold,
                                   "model_dir": model_info["model_dir"]})
    logger = run.logger(cfg["logger"]["backend"], **cfg["logger"]["kwargs"])
    total, every = cfg["train"]["total_frames"], cfg["eval"]["every_frames"]
    env.set_seed(cfg["seed"] + run.frames)
    if run.frames < total and not run.records and cfg["eval"]["at_start"]:
        run.records.append(evaluate())
        run.checkpoint(agent)

    # collect -> update -> evaluate -> log / checkpoint
    t_train, frames0, train_time = time.time(), run.frames, 0.0
    if run.frames < total:
        collector = env_collector(env, agent, total - run.frames, frames_done=run.frames, device=device)
        bar = tqdm(total=total, initial=run.frames, unit="frame", desc=algo["name"])
        next_eval = (run.frames // every + 1) * every
        for batch in collector:
            t0 = time.time()
            agent.set_progress(run.frames / total)  # before this batch counts: schedules (e.g. anneal_lr) follow the frame budget
            run.frames += batch.numel()
            metrics = agent.update(batch)
            run.updates += int(metrics.pop("updates"))
            train_time += time.time() - t0
            if logger is not None:
                for k, v in {**metrics, **model_env_metrics(batch)}.items():
                    logger.log_scalar(k, v, step=run.frames)
            bar.update(batch.numel())
            if run.frames >= next_eval or run.frames >= total:
                run.records.append(evaluate(final=run.frames >= total))
                if logger is not None:
                    logger.log_scalar("eval/return_mean", run.records[-1]["return_mean"], step=run.frames)
                bar.set_postfix(ret=f"{run.records[-1]['return_mean']:.0f}")
                run.checkpoint(agent)
                next_eval = (run.frames // every + 1) * every
        bar.close()
        collector.shutdown()
    if not run.records or not all((run.path / f).is_file() for f in agent.evaluation_files):
        run.records[-1:] = [evaluate(final=True)]
        run.checkpoint(agent)

    # report
    behaviour = data.return_stats()
    plot_curve([run.records], run.path / "learning_curve.png", label=algo["name"], behaviour=behaviour["mean"],
               title=f"{algo['name']} on {env_cfg['env_id']} ({cfg['dataset']})")
    elapsed = time.time() - t_train
    summary = run_summary(
        cfg, data, behaviour, run.records, ref=evaluator.ref, pessimism=pessimism, threshold=env.base_env.threshold,
        frames=run.frames, updates=run.updates, frames_per_s=(run.frames - frames0) / elapsed if run.frames > frames0 else None,
        updates_per_s=None, timing={"update_time_s": train_time, "data_s": t_data, "models_s": t_models, "total_s": time.time() - t_start},
        models=model_info["model_dir"], run_dir=run.path, evaluation_files=agent.evaluation_files,
    )
    run.write_json("summary.json", summary)
    eval_env.close()
    print("\n" + format_summary(summary))


if __name__ == "__main__":
    main()
