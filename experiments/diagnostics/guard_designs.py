"""Guard designs scored on kept rollouts: which paired model comparison tells a better policy from a worse one?

    python experiments/diagnostics/guard_designs.py FOLDER [--last-only] [--runs ROOT ...]

Reads the ``<run>.pt`` files of ``guard_rollouts.py`` (every kept policy and
the start of a run, each model episode step by step). For every design, the
comparison of a policy with the start is the smallest over the members of the
one-sided 95% lower bound on the mean paired difference of a per-episode
statistic (the shipped guard: the whole-length return, penalty included); the
guard passes a policy when that bound is above 0. Designs: the return
truncated at ``h`` steps (``h`` = the run's training horizon from the offline
rules, or a fixed count), with the pessimism's penalty (``-penalty`` on the
step that ends an episode) or without it (the episode still ends there: what
leaving the data costs is the reward it no longer collects). With
``--runs ROOT [ROOT ...]`` (folders holding the runs, to read each one's
dataset) the designs ``*_cap`` clip every episode's return, the start's and
the policy's, at the best return of a complete episode in the run's data
before pairing them: the model cannot vouch for a return the data never shows.

Printed per design, over every (run, policy) pair, or only the last policy
of each run (``--last-only``: what a run returns): passes and fires, how many
were right (checked with the runs' recorded real scores, after the fact), the
D4RL points the wrong ones cost, and the mean real score of what the guard
returns. The real scores are read to score a design, never inside one.
"""
from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import json

import torch

from torchrl_offhrl.recipes.selection import GAIN_Z as Z, paired_gain_lcb

_BEST: dict = {}


def data_best_return(run_name: str, roots: list[Path]) -> float:
    """The guard's return cap of the run ``run_name`` (its ``config.json`` under one of ``roots``): the library's own
    :func:`~torchrl_offhrl.recipes.selection.data_return_cap` on the run's data and ``eval.max_steps``."""
    from torchrl_offhrl.recipes.config import resolve_dataset
    from torchrl_offhrl.recipes.selection import data_return_cap

    found = [r / run_name for r in roots if (r / run_name / "config.json").exists()]
    if not found:
        raise FileNotFoundError(f"no {run_name}/config.json under {', '.join(map(str, roots))}")
    cfg = json.loads((found[0] / "config.json").read_text())
    key = (cfg["env"]["name"], str(cfg["dataset"]), cfg.get("dataset_seed"), cfg.get("num_transitions"), int(cfg["eval"]["max_steps"]))
    if key not in _BEST:
        _BEST[key] = float(data_return_cap(resolve_dataset(cfg), key[-1]))
    return _BEST[key]


def worst_member_lcb(diff: torch.Tensor, member: torch.Tensor, z: float = Z, pooled: bool | str = False) -> float:
    """The shipped guard's bound (:func:`~torchrl_offhrl.recipes.selection.paired_gain_lcb`) on per-episode differences
    ``diff``; ``pooled``: every episode as one sample; ``"agree"``: the pooled bound and no member's mean gain below 0."""
    if pooled == "agree":
        return min(worst_member_lcb(diff, member, z, True), worst_member_lcb(diff, member, 0.0, False))
    members = [0] * len(member) if pooled else [int(k) for k in member]
    return paired_gain_lcb({"model_episode_returns": diff.tolist(), "model_episode_members": members},
                           {"model_episode_returns": [0.0] * len(members), "model_episode_members": members}, z=z)


def per_episode(p: dict, h: int | None, penalty: bool) -> torch.Tensor:
    r = p["reward"].double()
    if not penalty:
        r = torch.where(p["penalized"], torch.zeros_like(r), r)
    if h is not None:
        r = r[:, :h]
    return r.sum(1)


def designs(run: dict, cap: bool = False) -> dict:
    H = int(run["config"]["resolved_model_env"]["horizon"])
    out = {}
    if cap:
        out["whole_pen_cap"] = (None, True, False, True)
        out["h50_pen_cap"] = (50, True, False, True)
        out["whole_pool_pen_cap"] = (None, True, True, True)
    for pooled in (False, True, "agree"):
        for pen in (True, False):
            tag = ("agree_" if pooled == "agree" else "pool_" if pooled else "") + ("pen" if pen else "nopen")
            out[f"whole_{tag}"] = (None, pen, pooled, False)
            out[f"hrule_{tag}"] = (H, pen, pooled, False)
            out[f"2hrule_{tag}"] = (2 * H, pen, pooled, False)
            for h in (50, 100, 200, 300):
                out[f"h{h}_{tag}"] = (h, pen, pooled, False)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--last-only", action="store_true")
    ap.add_argument("--match", default="", help="only runs whose name contains this")
    ap.add_argument("--show", nargs="*", default=[], help="designs to break down per run group (algo-env-level)")
    ap.add_argument("--runs", nargs="*", type=Path, default=[], help="folders holding the runs (for the *_cap designs)")
    a = ap.parse_args(argv)
    rows = defaultdict(list)  # design -> (group, gain_real, lcb, start_real, policy_real)
    groups = set()
    for f in sorted(a.folder.glob("*.pt")):
        if a.match not in f.name:
            continue
        run = torch.load(f, weights_only=True)
        start, pols = run["policies"][0], run["policies"][1:]
        if a.last_only:
            pols = pols[-1:]
        group = f.stem.rsplit("-d", 1)[0]
        groups.add(group)
        best = data_best_return(f.stem, a.runs) if a.runs else None
        for name, (h, pen, pooled, cap) in designs(run, cap=best is not None).items():
            s0 = per_episode(start, h, pen)
            if cap:
                s0 = s0.clamp(max=best)
            for p in pols:
                r = per_episode(p, h, pen)
                lcb = worst_member_lcb((r.clamp(max=best) if cap else r) - s0, p["member"], pooled=pooled)
                rows[name].append((group, p["real"] - start["real"], lcb, start["real"], p["real"]))
    print(f"{'design':16s} {'n':>4s} {'pass':>5s} {'right':>6s} {'cost':>7s} {'fire':>5s} {'right':>6s} {'cost':>7s} {'returned':>9s} {'start':>6s} {'policy':>7s}")
    for name, rs in rows.items():
        passed = [r for r in rs if r[2] > 0]
        fired = [r for r in rs if r[2] <= 0]
        pr = sum(r[1] > 0 for r in passed)
        fr = sum(r[1] <= 0 for r in fired)
        pcost = sum(-r[1] for r in passed if r[1] <= 0)
        fcost = sum(r[1] for r in fired if r[1] > 0)
        ret = sum(r[4] if r[2] > 0 else r[3] for r in rs) / len(rs)
        print(f"{name:16s} {len(rs):4d} {len(passed):5d} {pr:6d} {pcost:7.1f} {len(fired):5d} {fr:6d} {fcost:7.1f} {ret:9.2f} "
              f"{sum(r[3] for r in rs) / len(rs):6.2f} {sum(r[4] for r in rs) / len(rs):7.2f}")
    for name in a.show:
        print(f"\n{name}: per group, mean real score (start / policy / returned) and passes (right)")
        for g in sorted(groups):
            rs = [r for r in rows[name] if r[0] == g]
            ret = sum(r[4] if r[2] > 0 else r[3] for r in rs) / len(rs)
            print(f"  {g:34s} n {len(rs):3d} start {sum(r[3] for r in rs) / len(rs):6.1f} policy {sum(r[4] for r in rs) / len(rs):6.1f} "
                  f"returned {ret:6.1f} passes {sum(r[2] > 0 for r in rs)} ({sum(r[2] > 0 and r[1] > 0 for r in rs)} right)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
