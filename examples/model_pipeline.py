"""The model pipeline end to end: dataset -> ensemble + CVAE -> composed env -> rollout.

    python examples/model_pipeline.py                       # embedded default (Hopper-v5, random data)
    python examples/model_pipeline.py dataset=my.hdf5       # your own D4RL-style file
    python examples/model_pipeline.py dataset=medium 'model_env.pessimism={fraction: 1.08, penalty: 20}'
    python examples/model_pipeline.py env=halfcheetah num_transitions=20000

Steps: collect (or load) a dataset, fit the dynamics ensemble and the CVAE
(cached), compose ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)``,
check its specs, print the calibration report (with a histogram PNG), roll out
the CVAE prior as a policy in the model and in the real env, and compare.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import check_env_specs

from torchrl_offhrl.recipes.config import model_config, model_env_config, offline_rules_for, resolve_dataset
from torchrl_offhrl.recipes.pipeline import (
    GaussianLatentPolicy,
    fit_or_load_models,
    make_model_env,
    make_real_env,
)
from torchrl_offhrl.scores import normalized_score


def episode_returns(td) -> tuple[torch.Tensor, dict]:
    """Returns of the episodes that finished in a [B, T] rollout (with auto-reset), and how they ended."""
    done = td["next", "done"].squeeze(-1)
    rew = td["next", "reward"].squeeze(-1)
    # cumulative reward since each env's last episode start
    returns, ends = [], {"penalty": 0, "terminated": 0, "truncated": 0}
    acc = torch.zeros(rew.shape[0])
    for t in range(rew.shape[1]):
        acc += rew[:, t]
        d = done[:, t]
        if d.any():
            returns.append(acc[d])
            pen = td["next", "penalized"][:, t].squeeze(-1)[d] if ("next", "penalized") in td.keys(True) else None
            term = td["next", "terminated"][:, t].squeeze(-1)[d]
            if pen is not None:
                ends["penalty"] += int(pen.sum())
                ends["terminated"] += int((term & ~pen).sum())
            else:
                ends["terminated"] += int(term.sum())
            ends["truncated"] += int((~term).sum())
            acc[d] = 0
    return (torch.cat(returns) if returns else torch.zeros(0)), ends


@hydra.main(config_path="../configs", config_name="pipeline", version_base=None)
def main(cfg: DictConfig) -> None:
    t_start = time.time()
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)

    data = resolve_dataset(cfg)
    print(data)
    t_data = time.time()
    mcfg = model_config(cfg)  # the same settings (and so the same cached models) as `offhrl train`
    ensemble, cvae, info = fit_or_load_models(mcfg, data)
    t_fit = time.time()
    for name in ("ensemble", "cvae"):
        hist = info.get(f"{name}_history")
        if hist:
            last = hist[-1]
            val = last.get("val_loss")
            print(f"{name}: {info[name]} in {last['steps']} steps; validation loss per member: "
                  f"{[round(v, 4) for v in val] if val else 'n/a'}")
        else:
            print(f"{name}: loaded from {info['model_dir']}")

    plain = OmegaConf.to_container(cfg, resolve=True)
    rules = offline_rules_for(plain, data, ensemble, cvae)  # the `auto` settings from the data and the models
    mcfg["env"], _ = model_env_config(plain, data.metadata.get("level"), data, rules=rules)
    env = make_model_env(mcfg, ensemble, cvae, data, batch_size=cfg.rollout.batch_size)
    threshold = env.base_env.threshold  # calibrated once, reused
    check_env_specs(make_model_env(mcfg, ensemble, cvae, data, batch_size=None, threshold=threshold))
    check_env_specs(make_model_env(mcfg, ensemble, cvae, data, batch_size=4, threshold=threshold))
    print("check_env_specs: passed (unbatched and batched)")
    base = env.base_env
    print("\n== calibration ==")
    if rules is not None:
        print(rules.summary())
        rules.plot(out_dir / "offline_rules.png")
    print(base.calibration_report(plot_path=out_dir / "calibration.png"))

    policy = GaussianLatentPolicy(cvae.latent_dim)
    env.set_seed(cfg.seed)
    t0 = time.time()
    with torch.no_grad():
        td = env.rollout(cfg.rollout.steps, policy, break_when_any_done=False)
    dt = time.time() - t0
    model_returns, ends = episode_returns(td)
    n_tr = td.numel()

    real = make_real_env(cfg.env.env_id, cvae, num_envs=cfg.rollout.real_envs, latent_bound=mcfg["env"]["latent_bound"])
    real.set_seed(cfg.seed + 1)
    with torch.no_grad():  # finished episodes auto-reset; only completed ones are counted
        rtd = real.rollout(cfg.rollout.real_steps, policy, break_when_any_done=False)
    real_returns, _ = episode_returns(rtd)
    real.close()

    behaviour = data.episode_returns()
    rows = [
        ("dataset (behaviour) return", behaviour.mean().item(), behaviour.std().item(), behaviour.numel()),
        ("CVAE prior policy, model return", model_returns.mean().item(), model_returns.std().item(), model_returns.numel()),
        ("CVAE prior policy, real return", real_returns.mean().item(), real_returns.std().item(), real_returns.numel()),
    ]
    print("\n== rollout ==")
    print(f"{n_tr} model transitions ({cfg.rollout.batch_size} envs x {cfg.rollout.steps} steps) in {dt:.1f}s "
          f"= {n_tr / dt:,.0f} transitions/s")
    print(f"model episodes ended by: pessimistic penalty {ends['penalty']}, task termination "
          f"{ends['terminated']}, horizon {ends['truncated']}")
    print(f"\n{'':34s} {'mean':>9s} {'std':>9s} {'episodes':>9s} {'D4RL-norm':>10s}")
    for name, m, s, n in rows:
        ns = normalized_score(cfg.env.env_id, m)
        print(f"{name:34s} {m:9.1f} {s:9.1f} {n:9d} {ns if ns is None else round(ns, 1)!s:>10s}")
    summary = {
        "config": OmegaConf.to_container(cfg, resolve=True),
        "dataset": {"transitions": len(data), "episodes": data.num_episodes, "return_mean": behaviour.mean().item()},
        "calibration": base.calibration.as_dict(),
        "offline_rules": None if rules is None else rules.as_dict(),
        "rollout": {"transitions": n_tr, "seconds": dt, "episode_ends": ends},
        "returns": {name: {"mean": m, "std": s, "episodes": n} for name, m, s, n in rows},
        "timing_s": {"data": t_data - t_start, "fit": t_fit - t_data, "total": time.time() - t_start},
        "models": info["model_dir"],
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(f"\ntotal {time.time() - t_start:.0f}s; outputs: {out_dir}/summary.json, {out_dir}/calibration.png; "
          f"models cached in {info['model_dir']}")


if __name__ == "__main__":
    main()
