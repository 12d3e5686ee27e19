"""Model-free offline RL on the dataset itself (IQL, CQL, TD3+BC, BC), read top to bottom.

    python examples/offline_baseline.py algo=iql env=hopper dataset=medium
    python examples/offline_baseline.py algo=td3bc env=halfcheetah dataset=medium train.total_updates=100000
    python examples/offline_baseline.py algo=bc dataset=/data/hopper_medium.hdf5 seed=1

config -> data -> agent -> minibatches of the dataset -> update -> evaluate -> log / checkpoint.
No world model and no CVAE: these are the peers the offline hierarchical agents are compared
with, trained on the same data and evaluated the same way (real env, deterministic, the same
episodes and seeds as `offhrl train algo=moc`). The budget counts gradient steps
(train.total_updates, eval.every_updates). Outputs go to outputs/runs/<algo>-<env>-<dataset>-seed<seed>/;
running the same command again resumes. `offhrl train algo=iql ...` runs the same recipe.
"""
import time

import hydra
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.recipes.config import config_fingerprint, default_run_dir, learns_from_dataset, resolve_dataset, resolve_reward_scale
from torchrl_offhrl.recipes.evaluation import Evaluator
from torchrl_offhrl.recipes.pipeline import make_real_env
from torchrl_offhrl.recipes.report import UNIT_LABELS, format_summary, plot_curve, run_summary
from torchrl_offhrl.recipes.rundir import RunDirectory
from torchrl_offhrl.recipes.sources import dataset_batches
from torchrl_offhrl.utils import to_plain


@hydra.main(config_path="../configs", config_name="offline_train", version_base=None)
def main(cfg: DictConfig) -> None:
    # config
    cfg = to_plain(cfg)
    if not learns_from_dataset(cfg):
        raise SystemExit(f"algo={cfg['algo']['name']} trains on the model env: use examples/offline_train.py")
    t_start = time.time()
    algo, env_cfg = dict(cfg["algo"]), cfg["env"]
    run = RunDirectory(cfg.get("run_dir") or default_run_dir(cfg), config_fingerprint(cfg))
    run.unit = "updates"
    device = torch.device(cfg["device"])
    torch.manual_seed(cfg["seed"])

    # data: a level name (generated and cached), an HDF5 file or a local Minari id
    data = resolve_dataset(cfg)
    if "reward_scale" in algo:  # e.g. IQL's return_range: 1000 / (max - min episode return)
        algo["reward_scale"] = resolve_reward_scale(algo["reward_scale"], data, algo.get("gamma", 0.99))

    # the agent acts in the real env's actions; evaluation: deterministic, real env, the recipe's seeds
    eval_env = make_real_env(env_cfg["env_id"], None, num_envs=cfg["eval"]["episodes"])
    stats = data.stats()
    agent = make_agent(algo["name"], eval_env, algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std, action_key="action", device=device)
    agent.attach(eval_env)
    evaluator = Evaluator(eval_env, env_cfg["env_id"], cfg["eval"]["episodes"], cfg["eval"]["max_steps"], seed=cfg["seed"] * 1000 + 7)

    def evaluate():
        rec = {"frames": run.frames, "updates": run.updates, "step": run.updates, "wall_s": round(time.time() - t_start, 1)}
        return {**rec, **evaluator(agent)}

    # checkpoint and logs: rerunning the command resumes (the sampling RNG included)
    run.data_hash = data.content_hash()
    run.resume(agent, device)
    run.write_json("config.json", {**cfg, "resolved_reward_scale": algo.get("reward_scale"), "data_hash": run.data_hash, "unit": "updates"})
    logger = run.logger(cfg["logger"]["backend"], **cfg["logger"]["kwargs"])
    total, every = cfg["train"]["total_updates"], cfg["eval"]["every_updates"]
    if run.updates < total and not run.records and cfg["eval"]["at_start"]:
        run.records.append(evaluate())
        run.checkpoint(agent)

    # sample -> update -> evaluate -> log / checkpoint
    t_train, updates0 = time.time(), run.updates
    bar = tqdm(total=total, initial=run.updates, unit="update", desc=algo["name"])
    for batch in dataset_batches(data, agent, total - run.updates, device=device):
        run.frames += batch.numel()
        metrics = agent.update(batch)
        run.updates += int(metrics.pop("updates"))
        bar.update(1)
        if logger is not None and run.updates % 1000 == 0:
            for k, v in metrics.items():
                logger.log_scalar(k, float(v), step=run.updates)
        if run.updates % every == 0 or run.updates >= total:
            run.records.append(evaluate())
            bar.set_postfix(ret=f"{run.records[-1]['return_mean']:.0f}")
            run.checkpoint(agent)
    bar.close()

    # report
    behaviour = data.return_stats()
    plot_curve([run.records], run.path / "learning_curve.png", label=algo["name"], behaviour=behaviour["mean"],
               title=f"{algo['name']} on {env_cfg['env_id']} ({cfg['dataset']})", xlabel=UNIT_LABELS["updates"])
    elapsed = time.time() - t_train
    summary = run_summary(
        cfg, data, behaviour, run.records, ref=None, pessimism=None, threshold=None, frames=run.frames, updates=run.updates,
        frames_per_s=None, updates_per_s=(run.updates - updates0) / elapsed if run.updates > updates0 else None,
        timing={"total_s": time.time() - t_start}, models=None, run_dir=run.path, unit="updates",
    )
    run.write_json("summary.json", summary)
    eval_env.close()
    print("\n" + format_summary(summary))


if __name__ == "__main__":
    main()
