"""The demo's model fits against a step budget: what stopping earlier would save, and what it costs the models (issue 75).

    python benchmarks/fit_budget.py [--threads N] [--config demo] [--budgets 5000 10000 20000 30000] [OVERRIDE ...]

Fits the ensemble and the CVAE of ``configs/<config>.yaml`` (the demo's: MLP(256, 256), 100,000 hopper-medium
transitions of dataset seed 0) as ``offhrl demo`` fits them, to the shipped convergence rule on the held-out episodes,
through :func:`~torchrl_offhrl.recipes.pipeline.fit_or_load_models` with an empty model cache of its own (the dataset
comes from the usual cache: ``$TORCHRL_OFFHRL_CACHE``), and prints from each fit's per-epoch history:

* when the rule stopped it (steps, epochs, minutes of this run) and its held-out loss (the members' mean);
* for each step budget (``--budgets``, the stretch of a fit a shorter demo could afford): the held-out loss the fit had
  reached by then, relative to the converged one, and the minutes that budget takes at this run's rate (a fit's steps
  cost the same throughout, so the time at step ``s`` is the total's share ``s / steps``).

What the demo does with less converged models is a separate, longer measurement (the demo's robustness runs,
``offhrl results robustness``); the ones made so far are quoted in ``benchmarks/README.md`` beside this table.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=None, help="torch threads for the fits (default: the config's fit_threads)")
    p.add_argument("--config", default="demo")
    p.add_argument("--budgets", nargs="+", type=int, default=[5000, 10000, 20000, 30000])
    p.add_argument("overrides", nargs="*", help="hydra overrides of the config (e.g. num_transitions=5000 for a quick check)")
    a = p.parse_args()
    import torch

    from torchrl_offhrl.recipes.config import compose, model_config, resolve_dataset
    from torchrl_offhrl.recipes.pipeline import fit_or_load_models

    cfg = compose(a.config, a.overrides)
    data = resolve_dataset(cfg)  # from the usual cache (generated there on first use)
    mcfg = model_config(cfg)
    if a.threads:
        mcfg["fit_threads"] = a.threads
    models = tempfile.mkdtemp(prefix="fit_budget_")
    os.environ["TORCHRL_OFFHRL_CACHE"] = models  # models only: the fits below are fresh, and their cache is thrown away
    info, minutes = {}, {}
    for name, with_cvae in (("ensemble", False), ("cvae", True)):  # the second call loads the ensemble, fits the CVAE
        t = time.perf_counter()
        info.update(fit_or_load_models(mcfg, data, with_cvae=with_cvae)[2])
        minutes[name] = (time.perf_counter() - t) / 60
    print(f"\ntorch {torch.__version__}, fit threads {mcfg.get('fit_threads') or torch.get_num_threads()}; configs/{a.config}.yaml, "
          f"{len(data)} transitions\n")
    print("| model | stopped by the rule at step (epoch) | minutes (this run) | held-out loss there | budget (steps) | "
          "held-out loss at the budget, vs converged | minutes at the budget |")
    print("|---|---|---|---|---|---|---|")
    for name in ("ensemble", "cvae"):
        hist = info.get(f"{name}_history") or []
        if not hist:
            print(f"| {name} | (loaded, not fitted) | | | | |")
            continue
        mean = lambda r: sum(r["val_loss"]) / len(r["val_loss"])  # noqa: E731
        best = min(mean(r) for r in hist)
        last = hist[-1]
        for b in a.budgets:
            reached = [r for r in hist if r["steps"] <= b]
            at = min(mean(r) for r in reached) if reached else float("nan")
            rel = f"{(at - best) / abs(best):+.1%}" if reached else "before the first epoch"
            at_budget = minutes[name] * min(b, last["steps"]) / last["steps"]
            print(f"| {name} | {last['steps']} ({last['epoch'] + 1}) | {minutes[name]:.1f} | {best:.4f} | {b} | {rel} | {at_budget:.1f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
