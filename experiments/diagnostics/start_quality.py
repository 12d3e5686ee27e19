"""How good a behaviour cloner is a run's start, the policy the guard falls back to? Next to a plain %BC of the same episodes.

    python experiments/diagnostics/start_quality.py RUN_DIR [RUN_DIR ...] [--episodes 50] [--out FILE.json]

The start (``model_env.latent_origin=best``) decodes the CVAE at the latent
origin: ``decoder(s, z_b(s))``, ``z_b`` a regression of the posterior means
of the data's best episodes (``origin_share`` of the transitions). Per run,
on the held-out episodes of those best episodes (the run's own episode split
and seed), the mean absolute action error in units of the data's action std
of:

* ``start``: the run's start, as it acts;
* ``posterior``: the decoder at each pair's own posterior mean (what the
  decoder can reproduce at best; it needs the action, so no policy);
* ``through``: an origin fitted *through* the frozen decoder on the decoded
  action's error (from the shipped origin's weights);
* ``bc``: a plain MLP (256, 256) from the state to the action, squashed to
  the action box, on the same transitions (percentile BC, Chen et al. 2021).

Both fits stop on the held-out error (checked every 500 steps, patience 5).
Then each of ``start``, ``through`` and ``bc`` is rolled out
deterministically for ``--episodes`` real-env episodes (the same seeds for
all three): a diagnostic, on design data only; nothing here chooses a
default.
"""
from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from torchrl_offhrl.data import OfflineDataset
from torchrl_offhrl.nets import mlp
from torchrl_offhrl.recipes.config import resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.scores import normalized_score


def _fit(fn, params, s, a, vs, va, scale, seed: int, steps: int = 20000, batch: int = 256) -> float:
    """Adam on the L1 action error in ``scale`` units; the parameters of the best held-out check are kept."""
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(params, lr=1e-3)
    best, kept, bad = float("inf"), [p.detach().clone() for p in params], 0
    for i in range(steps):
        idx = torch.randint(len(s), (batch,), generator=g)
        loss = ((fn(s[idx]) - a[idx]).abs() / scale).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i % 500 == 499:
            with torch.no_grad():
                v = float(((fn(vs) - va).abs() / scale).mean())
            if v < best - 1e-4:
                best, bad, kept = v, 0, [p.detach().clone() for p in params]
            else:
                bad += 1
                if bad >= 5:
                    break
    with torch.no_grad():
        for p, k in zip(params, kept):
            p.copy_(k)
    return best


def _real(env_id: str, policy, episodes: int, seed: int = 1000, max_steps: int = 1000) -> list[float]:
    envs = gym.vector.SyncVectorEnv([lambda: gym.make(env_id) for _ in range(episodes)])
    obs, _ = envs.reset(seed=seed)
    ret, done = np.zeros(episodes), np.zeros(episodes, bool)
    for _ in range(max_steps):
        with torch.no_grad():
            act = policy(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        obs, r, term, trunc, _ = envs.step(act)
        ret += r * ~done
        done |= term | trunc
        if done.all():
            break
    envs.close()
    return ret.tolist()


def probe(run: Path, episodes: int) -> dict:
    cfg, env, _, _, cvae = load_run_agent(run, num_envs=1)
    env.close()
    seed = int(cfg["seed"])
    torch.manual_seed(seed)
    data = resolve_dataset(cfg)
    share = float((cfg.get("model_env") or {}).get("origin_share", 0.1))
    mask, _ = data.top_return_episodes(share)
    best = OfflineDataset(data.data[mask], metadata=data.metadata, action_bounds=(data.action_low, data.action_high))
    train, val = best.split(0.1, seed)
    s, a, vs, va = train.data["observation"], train.data["action"], val.data["observation"], val.data["action"]
    scale = data.data["action"].std(0)
    dec = cvae.decoder.eval().requires_grad_(False)
    origin, bound = dec._origin

    def err(pred):
        return float(((pred - va).abs() / scale).mean())

    def start(obs):
        return dec(obs, torch.zeros(len(obs), dec.latent_dim))

    with torch.no_grad():
        out = {"run": run.name, "val_transitions": len(vs), "err_start": err(start(vs))}
        dec.set_origin(None)
        out["err_posterior"] = err(dec(vs, cvae.encode(vs, va)[0].clamp(-bound, bound)))
        dec.set_origin(origin, bound)
    through_origin = copy.deepcopy(origin).requires_grad_(True).train()

    def through(obs):
        cond = dec.condition(obs)
        return dec.squash(dec.net(torch.cat([cond, through_origin(cond).clamp(-bound, bound)], -1)))

    out["err_through"] = _fit(through, list(through_origin.parameters()), s, a, vs, va, scale, seed)
    net = mlp(s.shape[-1], a.shape[-1], [256, 256], "relu")
    om, osd = data.data["observation"].mean(0), data.data["observation"].std(0) + 1e-6
    lo, hi = data.action_low, data.action_high

    def bc(obs):
        return lo + (torch.tanh(net((obs - om) / osd)) + 1) * 0.5 * (hi - lo)

    out["err_bc"] = _fit(bc, list(net.parameters()), s, a, vs, va, scale, seed)
    env_id = cfg["env"]["env_id"]
    for name, policy in (("start", start), ("through", through), ("bc", bc)):
        rets = _real(env_id, policy, episodes)
        out[f"real_{name}"] = normalized_score(env_id, float(np.mean(rets)))
        out[f"real_{name}_se"] = float(np.std(rets, ddof=1) / np.sqrt(len(rets))) * abs(normalized_score(env_id, 1.0) - normalized_score(env_id, 0.0))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    rows = []
    for run in a.runs:
        r = probe(run, a.episodes)
        rows.append(r)
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}), flush=True)
        if a.out:
            a.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
