"""The transfer setting's runs (offline on forward-running data, then online on running backwards), then docs/results/transfer.md.

    offhrl results transfer run [--envs hopper] [--algos moc ppo sac] [--kinds transfer scratch] [--seeds 4 5 6]
    offhrl results transfer report      # docs/results/transfer.md, transfer.csv, curves.png
    offhrl results transfer sampled     # docs/results/transfer_sampled.md: final policies, deterministic vs sampled

Kinds of run (every one an ordinary run directory under ``outputs/results/transfer/``, resumable by rerunning):

* ``transfer``: the paper's setting. The offline phase is the ``demo`` scale of ``experiments/results/table1.py`` (100k generated
  ``medium`` transitions, demo-size models fitted 20k steps, 205k model-env frames), then ``--online-frames`` real-env
  frames (default 300k) on the ``backward`` task with the decoder discarded;
* ``scratch``: the same agent trained online only, from its initial weights, on the backward task (the baseline);
* ``keepdecoder``: fine-tuning through the CVAE decoder instead of discarding it (``transfer.decoder=keep``);
* ``nocvae``: the CVAE ablation (the paper's Fig. 5e): offline training in real actions (``ablation.no_cvae``), then the same online phase.

Seeds 4-6, as every results script here: nothing was tuned on them. The online phase is evaluated every 10k frames
(10 deterministic episodes, the same seeds at every evaluation); the report gives the return on the backward task at
the switch and 50k / 100k / 300k frames after it, the final and (apart) the best, and the mean over the online phase
(the area under the online curve divided by its length).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
from .table1 import BUDGET  # noqa: E402  (the demo scale's offline budget)

KINDS = {
    "transfer": ["transfer.task=backward"],
    "scratch": ["transfer.task=backward", "transfer.from_scratch=true"],
    "keepdecoder": ["transfer.task=backward", "transfer.decoder=keep"],
    "nocvae": ["transfer.task=backward", "ablation.no_cvae=true"],
}
OUT = ROOT / "outputs" / "results" / "transfer"
DOCS = ROOT / "docs" / "results" / "transfer"
ARCHIVE = DOCS / "runs"  # finished runs kept for good (outputs/ stays on the machine that ran them)
# --tuning: runs on the tuning seeds (default 1), with their own run directories, archive and page, never mixed with seeds 4-6
TUNING_OUT = ROOT / "outputs" / "results" / "transfer_tuning"
TUNING_ARCHIVE = DOCS / "tuning"
TUNING_PAGE = ROOT / "docs" / "results" / "transfer_tuning.md"


def run_dir(env: str, algo: str, kind: str, seed: int, tag: str | None = None, out: Path = OUT) -> Path:
    return out / f"{algo}-{env}-medium-{kind}{'-' + tag if tag else ''}-seed{seed}"


def run(envs: list[str], algos: list[str], kinds: list[str], seeds: list[int], online_frames: int,
        extra: list[str] = (), tag: str | None = None, tuning: bool = False) -> None:
    """Every (env, kind, algo, seed) run in turn; ``extra`` overrides go to every run, ``tag`` names such a variant
    (its run directories and its rows: ``algo.label=<algo>_<tag>``)."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.report import format_summary
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    out = TUNING_OUT if tuning else OUT
    for env in envs:
        for kind in kinds:
            for algo in algos:
                for seed in seeds:
                    overrides = [f"algo={algo}", f"env={env}", "dataset=medium", f"seed={seed}", f"run_dir={run_dir(env, algo, kind, seed, tag, out)}",
                                 *BUDGET["demo"], *KINDS[kind], f"transfer.online_frames={online_frames}", *extra,
                                 *([f"++algo.label={algo}_{tag}"] if tag else [])]
                    # (the demo's on-policy minibatch is left out by compose for the agents without one)
                    print(format_summary(train(to_plain(compose("demo", overrides)))), flush=True)
                    archive(tuning)


def archive(tuning: bool = False) -> list[Path]:
    """Archive every finished run under ``outputs/results/transfer/`` to ``docs/results/transfer/runs/<run>/``
    (``tuning``: ``outputs/results/transfer_tuning/`` to ``docs/results/transfer/tuning/``)."""
    from torchrl_offhrl.recipes.report import archive_runs

    return archive_runs(TUNING_OUT, TUNING_ARCHIVE) if tuning else archive_runs(OUT, ARCHIVE)


def tuning_report() -> str:
    """``docs/results/transfer_tuning.md``: the table and curves of the runs on the tuning seeds (``run --tuning``)."""
    from torchrl_offhrl.recipes.report import aggregate

    archive(tuning=True)
    runs = sorted(d for d in TUNING_ARCHIVE.glob("*-seed*") if (d / "summary.json").is_file())
    if not runs:
        raise SystemExit(f"no finished runs under {TUNING_OUT} or {TUNING_ARCHIVE}: run `offhrl results transfer run --tuning` first")
    table = aggregate(runs, TUNING_ARCHIVE, made_by="offhrl results transfer report --tuning")
    text = "\n".join([
        "# Transfer: runs on the tuning seeds", "",
        "Made by `offhrl results transfer report --tuning` from the runs of `offhrl results transfer run --tuning ...` "
        "(archived to `docs/results/transfer/tuning/`). These runs look for why an agent learns as it does on the new task; "
        "they use the tuning seeds (not 4-6, the seeds of `docs/results/transfer.md`) and are never mixed into that page. "
        "A row named `<algo>_<tag>` is a variant run with `--tag <tag> --extra <overrides>`; its overrides are in each run's "
        "`config.json`. The seed-1 runs of `moc`, `moc_constlr`, `moc_lr3e-4-constlr` and `ppo` ran from an ad-hoc script with the "
        "same overrides before `--tuning` existed and were moved here (their `config.json` keeps the folder they ran in, and the "
        "variants got their `algo.label` on the move).", "",
        "Runs: " + ", ".join(f"`{d.name}`" for d in runs), "", table, "", "![curves](transfer/tuning/curves.png)", ""])
    TUNING_PAGE.write_text(text)
    return text


def report() -> str:
    import json

    from torchrl_offhrl.recipes.report import aggregate, group_key, load_run

    archive()
    runs = sorted(d for d in ARCHIVE.glob("*-seed*") if (d / "summary.json").is_file())
    legacy_path = DOCS / "legacy.json"
    legacy = json.loads(legacy_path.read_text()) if legacy_path.is_file() else {"rows": {}, "runs": {}}
    groups = {"|".join(group_key(load_run(d))) for d in runs}  # as the table's first four columns
    old_rows = {k: r for k, r in legacy["rows"].items() if k not in groups}  # a group rerun here replaces the earlier page's row
    if not runs and not old_rows:
        raise SystemExit(f"no finished runs under {OUT} or {ARCHIVE}: run `offhrl results transfer run` first")
    out = DOCS
    table = aggregate(runs, out, made_by="offhrl results transfer report") if runs else ""
    if old_rows:
        table = (table + "\n\n" if table else "") + (
            "Rows of an earlier version of this page (their run directories were lost between sessions; `transfer/legacy.json`; "
            "their curves: `transfer/legacy_curves.png`):\n\n" + "\n".join([legacy["header"], "|" + "---|" * 14, *old_rows.values()]))
    lines = ["# Transfer: offline on forward-running data, then online on running backwards", "",
             __doc__.split("Kinds of run")[1].split("\n", 1)[1].strip(), "",
             "Made by `offhrl results transfer report` from the finished runs, archived from `outputs/results/transfer/` to "
             "`docs/results/transfer/runs/`. "
             "Returns are raw real-env returns on the backward task (D4RL's normalisation is the forward task's); "
             "the offline column is the last evaluation of the offline phase on the forward task. On Hopper a return of about 1,000 "
             "on the backward task is the healthy reward of standing through the whole episode (1 per step) with no backward "
             "progress.", "",
             f"{len(runs)} archived run(s) and {{n_old}} from the earlier page so far: the `seeds` column says how many seeds each row has; kinds and algorithms "
             "without a row have not been run yet (the runs are long on CPU and span sessions).", "",
             table, "", *(["![curves](transfer/curves.png)", ""] if runs else []), *(["![earlier curves](transfer/legacy_curves.png)", ""] if old_rows else []),
             "Rows short of 3 seeds:", "", *(short_rows([d.name for d in runs] + list(legacy["runs"])) or ["None."]), "",
             "Per run (return on the backward task at the switch and at the end of the online phase):", ""]
    per_run = {}
    for d in runs:
        ev = json.loads((d / "evals.json").read_text())
        online = [e for e in ev if e.get("phase") == "online"]
        per_run[d.name] = (f"{online[0]['return_mean']:.1f} at the switch, {online[-1]['return_mean']:.1f} after "
                           f"{online[-1]['frames'] - online[0]['frames']} online frames")
    kinds = {"to-backward": "transfer", "scratch-backward": "scratch"}
    shown = {(a, e.split("-")[0].lower(), kinds.get(k, "?")) for a, e, _, k in (r.split("|") for r in old_rows)}
    for name, line in legacy["runs"].items():  # the lost runs of the rows printed from the earlier page
        algo, env, _, kind = name.rsplit("-seed", 1)[0].split("-", 3)
        if name not in per_run and (algo, env, kind) in shown:
            per_run[name] = f"{line} (earlier page)"
    lines += [f"- `{n}`: {line}" for n, line in sorted(per_run.items())]
    lines = [x.replace("{n_old}", str(sum(v.endswith("(earlier page)") for v in per_run.values()))) for x in lines]
    text = "\n".join(lines) + "\n"
    (ROOT / "docs" / "results" / "transfer.md").write_text(text)
    return text


# the rows the transfer setting asks for (issue 16: MOC, PPO, SAC on both envs, transferred and from scratch; the CVAE
# ablation on Hopper), each with >= 3 seeds; the page lists those short of them, with the reason where one is known
EXPECTED = [*((a, e, k) for a in ("moc", "ppo", "sac") for e in ("hopper", "halfcheetah") for k in ("transfer", "scratch")),
            ("moc", "hopper", "nocvae")]
SHORT_REASONS = {("sac", "halfcheetah"): "Running or queued on the CPU: SAC makes one gradient step per frame (~70 frames/s on one core), so "
                                         "each seed takes ~1.2 h from scratch and ~2.5 h with its offline phase; Hopper's rows came first."}


def short_rows(names: list[str]) -> list[str]:
    """Lines naming each EXPECTED row with fewer than 3 seeds among the run directory ``names``, and why."""
    lines = []
    for algo, env, kind in EXPECTED:
        n = sum(name.startswith(f"{algo}-{env}-medium-{kind}-seed") for name in names)
        if n < 3:
            why = SHORT_REASONS.get((algo, env), "Running or queued on the CPU.")
            lines.append(f"- {algo} on {env}, {kind}: {n} of 3 seeds. {why}")
    return lines


SAMPLED_PAGE = ROOT / "docs" / "results" / "transfer_sampled.md"


def sampled(envs: list[str], episodes: int = 10, seed: int = 12345) -> str:
    """Each finished run's final policy (its checkpoint in ``outputs/results/transfer/``) evaluated on its last task twice,
    deterministic and sampled, on the same ``episodes`` start states: docs/results/transfer_sampled.md and .json.

    The learning curves evaluate every agent deterministically (MOC: the likeliest option, ended where its termination
    probability passes 0.5, and its mean action); this says what that hides, for each algorithm alike.
    """
    import json

    import numpy as np

    from torchrl_offhrl.recipes.evaluation import evaluate_run

    cache = SAMPLED_PAGE.with_suffix(".json")
    done = json.loads(cache.read_text()) if cache.is_file() else {}
    for d in sorted(OUT.glob("*-seed[456]")):
        env = d.name.split("-")[1]
        if env not in envs or not (d / "summary.json").is_file() or not (d / "checkpoint.pt").is_file():
            continue
        stamp = (d / "summary.json").stat().st_mtime
        if {k: done.get(d.name, {}).get(k) for k in ("stamp", "episodes", "seed")} == {"stamp": stamp, "episodes": episodes, "seed": seed}:
            continue  # evaluated already, the same way, and the run has not moved since
        det, sto = (evaluate_run(d, episodes=episodes, seed=seed, deterministic=x) for x in (True, False))
        done[d.name] = {"stamp": stamp, "episodes": episodes, "seed": seed, "task": det.get("task"), "deterministic": det["return_mean"], "sampled": sto["return_mean"],
                        "sampled_std_over_episodes": sto["return_std"]}
        cache.write_text(json.dumps(done, indent=1))
        print(f"{d.name}: deterministic {det['return_mean']:.1f}, sampled {sto['return_mean']:.1f}", flush=True)
    groups = {}
    for name, r in done.items():
        if (r.get("episodes"), r.get("seed")) != (episodes, seed):
            continue  # measured another way (the page states one)
        groups.setdefault(name.rsplit("-seed", 1)[0], []).append((name.rsplit("-seed", 1)[1], r))

    def ms(xs):
        return f"{np.mean(xs):,.0f} ± {np.std(xs, ddof=1) if len(xs) > 1 else 0.0:,.0f}"

    lines = ["# Transfer: final policies evaluated deterministically and sampled", "",
             "Made by `offhrl results transfer sampled` from the runs' final checkpoints (`outputs/results/transfer/`): each is "
             f"evaluated on its last task (backward) on the same {episodes} start states (seed {seed}), once deterministically as the "
             "learning curves do (PPO and SAC: the mean action; MOC: the likeliest option, ended where its termination probability "
             "passes 0.5, and that option's mean action) and once sampling actions (and MOC's options and terminations) as in "
             "training, with torch's RNG seeded the same way. Returns on the backward task; mean ± std over seeds (ddof 1).", "",
             "| run | seeds | deterministic | sampled | sampled - deterministic | per seed (deterministic / sampled) |", "|---|---|---|---|---|---|"]
    for g, rs in sorted(groups.items()):
        det, sto = [r["deterministic"] for _, r in rs], [r["sampled"] for _, r in rs]
        per = ", ".join(f"{s}: {r['deterministic']:,.0f} / {r['sampled']:,.0f}" for s, r in sorted(rs))
        lines.append(f"| {g} | {len(rs)} | {ms(det)} | {ms(sto)} | {np.mean(sto) - np.mean(det):+,.0f} | {per} |")
    text = "\n".join(lines) + "\n"
    SAMPLED_PAGE.write_text(text)
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results transfer", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--envs", nargs="+", default=["hopper"])
    r.add_argument("--algos", nargs="+", default=["moc", "ppo", "sac"])
    r.add_argument("--kinds", nargs="+", choices=sorted(KINDS), default=["transfer", "scratch"])
    r.add_argument("--seeds", nargs="+", type=int, default=None, help="default 4 5 6 (--tuning: 1)")
    r.add_argument("--online-frames", type=int, default=300_000)
    r.add_argument("--extra", nargs="+", default=[], metavar="KEY=VALUE", help="config overrides for every run (a variant: name it with --tag)")
    r.add_argument("--tag", default=None, help="name of the variant: run directories <algo>-<env>-medium-<kind>-<tag>-seed<N>, rows <algo>_<tag>")
    r.add_argument("--tuning", action="store_true", help="runs on tuning seeds (default 1), kept apart: outputs/results/transfer_tuning/")
    rep = sub.add_parser("report")
    rep.add_argument("--tuning", action="store_true", help="the tuning runs' page, docs/results/transfer_tuning.md")
    smp = sub.add_parser("sampled", help="final policies evaluated deterministically and sampled: docs/results/transfer_sampled.md")
    smp.add_argument("--envs", nargs="+", default=["hopper", "halfcheetah"])
    smp.add_argument("--episodes", type=int, default=10)
    a = p.parse_args(argv)
    if a.cmd == "run":
        seeds = a.seeds if a.seeds is not None else [1] if a.tuning else [4, 5, 6]
        if a.tuning and set(seeds) & {4, 5, 6}:
            raise SystemExit("--tuning runs use the tuning seeds; seeds 4-6 are the evaluation seeds of docs/results/transfer.md")
        if a.extra and not a.tag:
            raise SystemExit("--extra makes a variant: name it with --tag, so that its runs and rows are not taken for the defaults'")
        run(a.envs, a.algos, a.kinds, seeds, a.online_frames, a.extra, a.tag, a.tuning)
    elif a.cmd == "sampled":
        print(sampled(a.envs, a.episodes))
    else:
        print(tuning_report() if a.tuning else report())
    return 0

