"""The offline training recipe shared by SAC, PPO and MOC.

``train(cfg)`` (driven by ``examples/offline_train.py`` / ``offhrl train``):

1. resolve the dataset (a file, a local Minari id, or a named dataset that is
   generated and cached on first use);
2. fit or load the cached dynamics ensemble and CVAE;
3. build ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)`` with
   the paper's per-dataset pessimism (``configs/env/*.yaml``);
4. build the agent (``configs/algo/*.yaml``) and train it with a TorchRL
   collector on the model env: on-policy (PPO, MOC: GAE over each batch,
   epochs of minibatches) or off-policy (SAC: replay buffer);
5. every ``eval.every_frames`` frames, evaluate deterministically in the real
   Gymnasium env through the same decoder; log (TorchRL logger), checkpoint
   atomically (an interrupted run resumes from it), and at the end draw the
   learning curve and, for MOC, the option-usage plot.
"""
from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..data import OfflineDataset, load_dataset
from ..scores import normalized_score
from ..utils import atomic_write
from .agents import make_agent
from .behaviour import evaluate_policy, first_episode_mask
from .pipeline import _plain, fit_or_load_models, make_model_env, make_real_env

__all__ = ["default_run_dir", "format_summary", "model_config", "pessimism_for", "resolve_dataset", "train"]

log = logging.getLogger(__name__)

# settings that may change between a run and its resumption; anything else must match the checkpoint
_RESUMABLE_KEYS = ("train", "eval", "logger", "run_dir", "out_root", "torch_threads", "device")


def resolve_dataset(spec: str, env_name: str, env_id: str, num_transitions: int | None = None, seed: int = 0) -> OfflineDataset:
    """A dataset from ``spec``: a file path, a local Minari id, or a level name.

    Level names (``medium``, ``hopper-medium``, ``medium-expert``, ...) are
    generated with the shipped behaviour policies on first use and cached
    (:func:`torchrl_offhrl.data.named_dataset`).
    """
    spec = str(spec)
    path = Path(spec).expanduser()
    if path.exists() or path.suffix in (".hdf5", ".h5"):
        return load_dataset(path, env_id=env_id)
    if "/" in spec:  # a Minari id such as mujoco/hopper/medium-v0
        return load_dataset(spec, env_id=env_id)
    from ..data.generate import LEVELS, named_dataset

    level = spec[len(env_name) + 1 :] if spec.startswith(env_name + "-") else spec
    if level not in LEVELS:
        raise ValueError(
            f"dataset={spec!r} is neither an existing file, a Minari id, nor a level name "
            f"({', '.join(LEVELS)}); give a path to an HDF5 file or one of those names."
        )

    return named_dataset(f"{env_name}-{level}", num_transitions=num_transitions, seed=seed)


def model_config(cfg: Mapping) -> dict:
    """The part of a recipe config that :func:`fit_or_load_models` reads (and keys its cache on)."""
    cfg = _plain(cfg)
    return {
        "seed": cfg.get("dataset_seed", 0),
        "device": str(cfg.get("device", "cpu")),
        "dataset": {"val_ratio": cfg.get("val_ratio", 0.1)},
        "ensemble": cfg["ensemble"],
        "cvae": cfg["cvae"],
    }


def pessimism_for(env_cfg: Mapping, level: str | None, overrides: Mapping | None = None) -> dict:
    """The P-MDP settings for a dataset level: the paper's table in ``env_cfg['pessimism']``, then overrides."""
    table = _plain(env_cfg.get("pessimism", {}))
    out = dict(table.get("default", {"quantile": 0.99, "penalty": 20.0}))
    if level and level in table:
        out = dict(table[level])
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    if "quantile" in overrides and "fraction" not in overrides:
        out.pop("fraction", None)  # asking for a quantile replaces the table's fraction
    out.update(overrides)
    if out.get("fraction") is not None:
        out.pop("quantile", None)
    return out


def default_run_dir(cfg: Mapping) -> Path:
    """``<out_root>/<algo>-<env>-<dataset>[-<ablations>]-seed<seed>``.

    A dataset given as a file or a Minari id is named by its stem plus a short
    hash of the full path, so two files with the same name never share a run.
    """
    spec = str(cfg["dataset"])
    ds = spec
    if "/" in spec or Path(spec).suffix:
        digest = hashlib.sha1(str(Path(spec).expanduser().resolve()).encode()).hexdigest()[:6]
        ds = f"{Path(spec).stem}-{digest}"
    abl = "".join(f"-{k}" for k, v in _plain(cfg.get("ablation", {})).items() if v)
    return Path(cfg.get("out_root", "outputs/runs")) / f"{cfg['algo']['name']}-{cfg['env']['name']}-{ds}{abl}-seed{cfg['seed']}"


def _sum_losses(out) -> torch.Tensor:
    return sum(v for k, v in out.items() if k.startswith("loss_"))


def _scalars(out, prefix="train/") -> dict:
    res = {}
    for k, v in out.items():
        if isinstance(v, torch.Tensor) and v.numel() == 1:
            res[prefix + k] = float(v.detach())
    return res


def _alive(td) -> torch.Tensor:
    """``[E, T]``: steps up to and including each env's first ``done``."""
    return first_episode_mask(td["next", "done"].reshape(td.batch_size[0], -1))


def option_usage(td, num_options: int) -> torch.Tensor:
    """``[T, n]``: the fraction of still-running episodes in which each option is active at each step.

    ``td`` is a ``[E, T]`` evaluation rollout of auto-resetting envs; steps
    after an env's first ``done`` are ignored, and ``T`` stops at the last
    step any episode is still running.
    """
    opt = td["option"].reshape(td.batch_size[0], -1)
    alive = _alive(td)
    onehot = torch.nn.functional.one_hot(opt, num_options).float() * alive.unsqueeze(-1)
    running = alive.sum(0)
    last = int(running.nonzero().max()) + 1 if running.any() else 0
    return (onehot.sum(0) / running.clamp_min(1).unsqueeze(-1))[:last]


def train(cfg: Mapping, progress: bool = True) -> dict:
    """Run one recipe end to end; returns the summary also written to ``run_dir/summary.json``."""
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.envs import RewardSum
    from torchrl.record.loggers import get_logger
    from tqdm.auto import tqdm

    from .report import plot_curve, plot_option_usage

    cfg = _plain(cfg)
    t_start = time.time()
    algo, env_cfg = cfg["algo"], cfg["env"]
    run_dir = Path(cfg.get("run_dir") or default_run_dir(cfg))
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg["seed"])
    device = torch.device(cfg.get("device", "cpu"))

    # 1-2. data and models
    # one dataset for every training seed: its own seed is dataset_seed
    data = resolve_dataset(cfg["dataset"], env_cfg["name"], env_cfg["env_id"], cfg.get("num_transitions"), cfg.get("dataset_seed", 0))
    level = data.metadata.get("level")
    t_data = time.time() - t_start
    pcfg = model_config(cfg)
    ensemble, cvae, model_info = fit_or_load_models(pcfg, data, progress=progress)
    t_models = time.time() - t_start - t_data

    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg["torch_threads"]))
    # the agent's initial weights do not depend on whether the models were fitted or loaded
    torch.manual_seed(cfg["seed"])

    # 3. the composed model env
    abl = cfg.get("ablation", {})
    latent = not abl.get("no_cvae", False)
    pess = pessimism_for(env_cfg, level, cfg.get("model_env", {}).get("pessimism"))
    if abl.get("no_pessimism", False):
        pess = {"threshold": float("inf"), "penalty": 0.0}
    menv_cfg = {k: v for k, v in cfg.get("model_env", {}).items() if k != "pessimism"}
    pcfg["env"] = {**menv_cfg, **pess}
    frames_per_batch = int(algo["frames_per_batch"])
    num_envs = int(cfg["collector"]["num_envs"])
    env = make_model_env(pcfg, ensemble, cvae if latent else None, data, batch_size=num_envs, latent=latent)
    threshold = env.base_env.threshold
    stats = data.stats()
    action_key = "latent_action" if latent else "action"
    agent = make_agent(algo["name"], env, algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std, action_key=action_key)
    agent.loss.to(device)
    for t in agent.env_transforms():
        env.append_transform(t)
    env.append_transform(RewardSum())  # ("next", "episode_reward"): model returns in the logs
    episodes = int(cfg["eval"]["episodes"])
    eval_env = make_real_env(env_cfg["env_id"], cvae if latent else None, num_envs=episodes, latent_bound=menv_cfg.get("latent_bound", 2.0))
    for t in agent.env_transforms():
        eval_env.append_transform(t)

    # resume
    ckpt_path = run_dir / "checkpoint.pt"
    records: list[dict] = []
    frames = updates = 0
    rb = None
    if not agent.on_policy:
        rb = ReplayBuffer(storage=LazyTensorStorage(int(algo.get("buffer_size", 1_000_000)), device=device), batch_size=int(algo["batch_size"]))
    fingerprint = json.dumps({k: v for k, v in cfg.items() if k not in _RESUMABLE_KEYS}, sort_keys=True, default=str)
    replay_name = None
    if ckpt_path.is_file():
        state = torch.load(ckpt_path, weights_only=True, map_location=device)
        if state.get("fingerprint") not in (None, fingerprint):
            raise ValueError(
                f"{run_dir} holds a checkpoint of a run with a different configuration (only {', '.join(_RESUMABLE_KEYS)} "
                f"may change when resuming); give another run_dir= or out_root=, or delete {ckpt_path} to start over"
            )
        agent.load_state_dict(state["agent"])
        frames, updates, records = int(state["frames"]), int(state["updates"]), list(state["records"])
        torch.set_rng_state(state["rng"])
        replay_name = state.get("replay")
        if rb is not None and replay_name is not None:
            if not (run_dir / replay_name).is_dir():
                raise FileNotFoundError(f"the checkpoint's replay buffer {run_dir / replay_name} is missing; delete {ckpt_path} to start over")
            rb.loads(run_dir / replay_name)
        print(f"resuming {run_dir} from its checkpoint at {frames} frames")
    with atomic_write(run_dir / "config.json") as tmp:
        Path(tmp).write_text(
            json.dumps({**cfg, "resolved_pessimism": pess, "threshold": threshold, "model_dir": model_info["model_dir"]}, indent=2, default=str)
        )

    logger = None
    if cfg.get("logger", {}).get("backend"):
        lcfg = cfg["logger"]
        if frames and lcfg["backend"] == "csv":
            _trim_csv_logs(run_dir / "logs", frames)
        logger = get_logger(lcfg["backend"], logger_name=str(run_dir), experiment_name="logs", **lcfg.get("kwargs", {}))

    total = int(cfg["train"]["total_frames"])
    eval_every = int(cfg["eval"]["every_frames"])
    remaining = max(total - frames, 0)
    env.set_seed(cfg["seed"] + frames)
    init_random = 0 if (agent.on_policy or frames) else int(algo.get("init_random_frames", 0))
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    ref = ref if None not in ref else None

    def evaluate(final: bool = False):
        rets, td = evaluate_policy(
            eval_env, agent.policy, episodes, max_steps=int(cfg["eval"]["max_steps"]), deterministic=True,
            seed=int(cfg["seed"]) * 1000 + 7, return_rollout=True,
        )
        rec = {
            "frames": frames,
            "updates": updates,
            "wall_s": round(time.time() - t_start, 1),
            "return_mean": float(rets.mean()),
            "return_std": float(rets.std()),
            "normalized_d4rl": normalized_score(env_cfg["env_id"], float(rets.mean())),
            "normalized_dataset": normalized_score(env_cfg["env_id"], float(rets.mean()), ref=ref) if ref else None,
        }
        if agent.options:
            usage = option_usage(td, agent.options)
            alive = _alive(td)
            rec["option_usage_mean"] = (torch.nn.functional.one_hot(td["option"].reshape(alive.shape), agent.options).float()[alive].mean(0)).tolist()
            if final:
                torch.save(usage, run_dir / "option_usage.pt")
                plot_option_usage(usage, run_dir / "option_usage.png", title=f"MOC option usage, {env_cfg['env_id']}, {cfg['dataset']}")
        return rec

    def checkpoint():
        # the replay buffer goes to a folder named by the frame count, written before the
        # checkpoint that names it; the previous one is deleted only after that
        nonlocal replay_name
        new_replay = None
        if rb is not None and len(rb):  # an empty buffer (the evaluation before training) has nothing to save
            new_replay = f"replay-{frames}"
            shutil.rmtree(run_dir / new_replay, ignore_errors=True)
            rb.dumps(run_dir / new_replay)
        state = {
            "agent": agent.state_dict(), "frames": frames, "updates": updates, "records": records,
            "rng": torch.get_rng_state(), "replay": new_replay, "fingerprint": fingerprint,
        }
        with atomic_write(ckpt_path) as tmp:
            torch.save(state, tmp)
        with atomic_write(run_dir / "evals.json") as tmp:
            Path(tmp).write_text(json.dumps(records, indent=1))
        if replay_name is not None and replay_name != new_replay:
            shutil.rmtree(run_dir / replay_name, ignore_errors=True)
        replay_name = new_replay

    t_train = time.time()
    frames_at_start, updates_at_start = frames, updates
    train_time = 0.0
    if remaining > 0 and not records and cfg["eval"].get("at_start", True):
        # the untrained agent: the starting point of the learning curve (with the CVAE: about the decoder's mean action)
        records.append(evaluate())
        checkpoint()
    if remaining > 0:
        collector = Collector(
            env,
            agent.policy,
            frames_per_batch=frames_per_batch,
            total_frames=remaining,
            init_random_frames=init_random,
            split_trajs=False,
            auto_register_policy_transforms=False,  # the envs are built with the transforms they need
            device=device,
        )
        bar = tqdm(total=total, initial=frames, desc=f"{algo['name']} on {env_cfg['name']}-{level}", disable=not progress, unit="frame")
        next_eval = (frames // eval_every + 1) * eval_every
        for batch in collector:
            t0 = time.time()
            frames += batch.numel()
            metrics = _update(agent, batch, algo, rb, frames, init_random)
            updates += metrics.pop("_updates")
            train_time += time.time() - t0
            done = batch["next", "done"]
            if done.any():
                metrics["train/model_episode_return"] = float(batch["next", "episode_reward"][done].mean()) if ("next", "episode_reward") in batch.keys(True) else float("nan")
            metrics["train/penalized_rate"] = float(batch["next", "penalized"].float().mean()) if ("next", "penalized") in batch.keys(True) else float("nan")
            if logger is not None:
                for k, v in metrics.items():
                    logger.log_scalar(k, v, step=frames)
            bar.update(batch.numel())
            if frames >= next_eval or frames >= total:
                rec = evaluate(final=frames >= total)
                records.append(rec)
                if logger is not None:
                    for k in ("return_mean", "normalized_d4rl"):
                        if rec[k] is not None:
                            logger.log_scalar(f"eval/{k}", rec[k], step=frames)
                bar.set_postfix(ret=f"{rec['return_mean']:.0f}", score=f"{rec['normalized_d4rl'] or 0:.1f}")
                bar.write(f"[{frames} frames] real {env_cfg['env_id']} return {rec['return_mean']:.1f} ± {rec['return_std']:.1f} (D4RL-normalised {rec['normalized_d4rl'] or float('nan'):.1f})")
                checkpoint()
                next_eval = (frames // eval_every + 1) * eval_every
        bar.close()
        collector.shutdown()
    elif not records:
        records.append(evaluate(final=True))
        checkpoint()
    if agent.options and not (run_dir / "option_usage.png").is_file():
        records[-1] = evaluate(final=True)
        checkpoint()
    elapsed = time.time() - t_train
    behaviour = data.return_stats()  # episodes cut short by the collection budget left out
    plot_curve([records], run_dir / "learning_curve.png", label=algo["name"], title=f"{algo['name']} on {env_cfg['env_id']} ({cfg['dataset']})", behaviour=behaviour["mean"])
    final = records[-1]
    summary = {
        "algo": algo["name"],
        "env_id": env_cfg["env_id"],
        "dataset": str(cfg["dataset"]),
        "level": level,
        "seed": cfg["seed"],
        "ablation": abl,
        "pessimism": pess,
        "threshold": threshold,
        "frames": frames,
        "updates": updates,
        "final": final,
        "initial": records[0] if records[0]["frames"] == 0 else None,
        "behaviour_return_mean": behaviour["mean"],
        "behaviour_return_std": behaviour["std"],
        "behaviour_episodes": behaviour["episodes"],
        "behaviour_normalized_d4rl": normalized_score(env_cfg["env_id"], behaviour["mean"]),
        "behaviour_normalized_dataset": normalized_score(env_cfg["env_id"], behaviour["mean"], ref=ref) if ref else None,
        "dataset_transitions": len(data),
        "dataset_policy": str(data.metadata.get("policy", "?")),
        "dataset_level": level,
        "frames_per_s": (frames - frames_at_start) / elapsed if elapsed > 0 and frames > frames_at_start else None,
        "updates_per_s": ((updates - updates_at_start) / train_time) if train_time > 0 else None,
        "update_time_s": round(train_time, 1),
        "data_s": round(t_data, 1),
        "models_s": round(t_models, 1),
        "total_s": round(time.time() - t_start, 1),
        "models": model_info["model_dir"],
        "run_dir": str(run_dir),
    }
    with atomic_write(run_dir / "summary.json") as tmp:
        Path(tmp).write_text(json.dumps(summary, indent=2, default=str))
    eval_env.close()
    return summary


def _update(agent, batch, algo: Mapping, rb, frames: int, init_random: int) -> dict[str, Any]:
    """One round of learning on a collected batch; returns averaged scalar metrics."""
    loss = agent.loss
    params = [p for g in (o.param_groups for o in agent.optimizers) for grp in g for p in grp["params"]]
    max_norm = algo.get("max_grad_norm")  # None or absent: no clipping
    acc: dict[str, float] = {}
    n = 0
    if agent.on_policy:
        with torch.no_grad():
            loss.value_estimator(batch)
        flat = batch.reshape(-1)
        mb = int(algo["minibatch_size"])
        for _ in range(int(algo["epochs"])):
            for idx in torch.randperm(flat.numel()).split(mb):
                out = loss(flat[idx])
                total = _sum_losses(out)
                for o in agent.optimizers:
                    o.zero_grad()
                total.backward()
                if max_norm:
                    torch.nn.utils.clip_grad_norm_(params, float(max_norm))
                for o in agent.optimizers:
                    o.step()
                for k, v in _scalars(out).items():
                    acc[k] = acc.get(k, 0.0) + v
                n += 1
    else:
        rb.extend(batch.reshape(-1))
        if frames >= init_random:
            for _ in range(max(1, round(batch.numel() * float(algo.get("utd_ratio", 1.0))))):
                out = loss(rb.sample())
                total = _sum_losses(out)
                for o in agent.optimizers:
                    o.zero_grad()
                total.backward()
                for o in agent.optimizers:
                    o.step()
                agent.target_updater.step()
                for k, v in _scalars(out).items():
                    acc[k] = acc.get(k, 0.0) + v
                n += 1
    res = {k: v / max(n, 1) for k, v in acc.items()}
    res["_updates"] = n
    return res


def evaluate_run(run_dir, episodes: int = 10, seed: int = 12345, frames_dir=None, deterministic: bool = True) -> dict:
    """Evaluate a run's checkpoint in the real env: returns, normalised scores, optional PNG frames.

    Rebuilds the agent from ``run_dir/config.json``, loads ``checkpoint.pt``
    and the run's CVAE from the model cache, and rolls ``episodes`` episodes
    out in the real Gymnasium env through the same decoder. With
    ``frames_dir``, the first episode is rendered (``rgb_array``; headless
    machines need ``MUJOCO_GL=egl`` or ``osmesa``) and saved as PNG frames.
    """
    from ..models import ConditionalVAE

    run = Path(run_dir)
    cfg_path, ckpt_path = run / "config.json", run / "checkpoint.pt"
    for p in (cfg_path, ckpt_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: {run} is not a (checkpointed) run directory of `offhrl train`")
    cfg = json.loads(cfg_path.read_text())
    env_id = cfg["env"]["env_id"]
    latent = not cfg.get("ablation", {}).get("no_cvae", False)
    cvae = None
    if latent:
        model_dir = cfg.get("model_dir")
        if model_dir is None and (run / "summary.json").is_file():
            model_dir = json.loads((run / "summary.json").read_text()).get("models")
        if model_dir is None:
            raise FileNotFoundError(f"{cfg_path} does not say which models the run used (written by an older version); train it again")
        cvae_path = Path(model_dir) / "cvae.pt"
        if not cvae_path.is_file():
            raise FileNotFoundError(f"the run's CVAE {cvae_path} is not in the model cache any more; rerun `offhrl fit` with the run's config")
        cvae = ConditionalVAE.load(cvae_path)
    bound = cfg.get("model_env", {}).get("latent_bound", 2.0)
    env = make_real_env(env_id, cvae, num_envs=episodes, latent_bound=bound)
    agent = make_agent(cfg["algo"]["name"], env, cfg["algo"], action_key="latent_action" if latent else "action")
    for t in agent.env_transforms():
        env.append_transform(t)
    state = torch.load(ckpt_path, weights_only=True, map_location="cpu")
    agent.load_state_dict(state["agent"])
    rets = evaluate_policy(env, agent.policy, episodes, max_steps=int(cfg["eval"]["max_steps"]), deterministic=deterministic, seed=seed)
    env.close()
    res = {
        "run_dir": str(run),
        "frames": int(state["frames"]),
        "episodes": episodes,
        "deterministic": deterministic,
        "return_mean": float(rets.mean()),
        "return_std": float(rets.std()),
        "normalized_d4rl": normalized_score(env_id, float(rets.mean())),
        "returns": [round(float(r), 2) for r in rets],
    }
    if frames_dir is not None:
        res["frames_dir"] = str(_render_episode(env_id, cvae, bound, agent, Path(frames_dir), int(cfg["eval"]["max_steps"]), seed, deterministic))
    return res


def _render_episode(env_id, cvae, bound, agent, out: Path, max_steps: int, seed: int, deterministic: bool) -> Path:
    import matplotlib.pyplot as plt
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    try:
        env = make_real_env(env_id, cvae, num_envs=1, latent_bound=bound, render_mode="rgb_array")
        for t in agent.env_transforms():
            env.append_transform(t)
        env.set_seed(seed)
        base = env.base_env._env  # the gymnasium vector env
        out.mkdir(parents=True, exist_ok=True)
        frames = [base.render()]
        mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(mode):
            env.rollout(max_steps, agent.policy, callback=lambda *_: frames.append(base.render()))
        for t, frame in enumerate(frames):
            frame = frame[0] if isinstance(frame, (tuple, list)) else frame
            plt.imsave(out / f"frame_{t:04d}.png", frame)
        env.close()
    except Exception as err:  # rendering needs an OpenGL backend
        raise RuntimeError(
            f"rendering {env_id} failed ({type(err).__name__}: {err}); on a headless machine set MUJOCO_GL=egl (GPU) "
            f"or MUJOCO_GL=osmesa (CPU, needs libosmesa) and try again"
        ) from err
    return out


def _fmt(x, spec=".1f") -> str:
    return "n/a" if x is None else format(x, spec)


def format_summary(summary: Mapping) -> str:
    """The one-paragraph result of a run, as printed by ``offhrl train`` and ``examples/offline_train.py``."""
    f = summary["final"]
    return (
        f"{summary['algo']} on {summary['env_id']} ({summary['dataset']}), {summary['frames']} frames: real return "
        f"{f['return_mean']:.1f} ± {f['return_std']:.1f}, D4RL-normalised {_fmt(f['normalized_d4rl'])} "
        f"(behaviour data: {_fmt(summary['behaviour_normalized_d4rl'])}); outputs in {summary['run_dir']}"
    )


def _trim_csv_logs(log_dir: Path, max_step: int) -> int:
    """Drop the rows of TorchRL CSV logs (``step,value`` lines) logged after ``max_step``.

    A resumed run restarts from its checkpoint, so the steps it logged between
    that checkpoint and the interruption would otherwise appear twice.
    Returns the number of rows dropped. Each file is rewritten atomically.
    """
    dropped = 0
    for csv in sorted(Path(log_dir).glob("**/*.csv")):
        lines = csv.read_text().splitlines()
        keep = [line for line in lines if not line or float(line.split(",", 1)[0]) <= max_step]
        if len(keep) != len(lines):
            dropped += len(lines) - len(keep)
            with atomic_write(csv) as tmp:
                Path(tmp).write_text("".join(line + "\n" for line in keep))
    return dropped

