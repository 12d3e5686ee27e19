"""Offline UOF on block stacking against SAC + HER and BC: resumable runs, then the per-goal table and figures.

    offhrl results blockstack run [--tasks blockstack2] [--datasets medium-expert medium] [--algos uof sac_her bc]
        [--seeds 4 5 6 7 8] [--ablations [no_cvae cvae_no_goal no_pessimism]] [--variants latent05] [--no-main] [--frames 40000]
    offhrl results blockstack report          # docs/results/block_stacking.md and its figures

Every run is an ordinary run directory of ``offhrl train`` under
``outputs/results/blockstack/`` (rerunning resumes from its checkpoint, so the
runs can go to the background and survive interruptions). ``outputs/`` stays
on the machine, so each finished run is archived at once to
``docs/results/blockstack/runs/<run>/`` (config, evaluations, summary, option
usage: commit them) and the report reads the archive. The groups of the
earlier page whose runs were lost between sessions are printed as it gave
them (``docs/results/blockstack/legacy.json``), followed by a section of the
runs archived since for the same (task, dataset), if any. The datasets are the
scripted ones of ``offhrl collect`` (``--transitions`` per level, 100k by
default: medium-expert holds twice as many) or, named ``uof-epoch20`` /
``uof-epoch50``, the paper's route: ``--transitions`` collected by the shipped
UOF policy of that epoch with the ``medium`` level's noise; the models the
paper's sizes (``configs/env/blockstack*.yaml``), fitted once and cached.

Budgets (CPU): UOF and SAC + HER collect ``--frames`` model-env frames
(16 envs x 25 steps per batch; UOF's 40 + 40 updates per 400 frames; SAC +
HER at 0.1 updates per frame too instead of SB3's 1, which this CPU cannot
afford: ~25 ms per update), evaluated 5 times; BC takes 20k gradient steps
on the dataset, evaluated every 4k. Every evaluation: 30 episodes per goal in
the real env through the run's decoder, deterministic, success within 25
steps (training's horizon, the paper's) and within 50 (UOF's tests).

``--ablations`` (all three, or those named) adds UOF on task 1 without the CVAE (``ablation.no_cvae``),
with a CVAE not conditioned on the sub-goal (``cvae.goal_key=null``) and
without pessimistic termination (``ablation.no_pessimism``), the paper's
Fig. 5 a-d. ``--variants`` adds UOF with a setting beyond the paper's on every task, dataset and seed asked
for (``latent05``: the latent box +-0.5 instead of +-2, so the low level stays near the decoder's mean action;
``docs/results/blockstack/uof_notes.md`` rows 13-14).

Seeds 4-8 by default (five, as every group of the results): nothing was chosen by looking at their
evaluations (the settings are UOF's, SB3's and the env configs'; the 200k budget and the ``latent05``
variant were chosen on the tuning seeds 1-3, ``uof_notes.md`` rows 2 and 14).
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
BASE = ROOT / "outputs" / "results" / "blockstack"
OUT = ROOT / "docs" / "results"
ARCHIVE = OUT / "blockstack" / "runs"
ABLATIONS = {"no_cvae": ["ablation.no_cvae=true"], "cvae_no_goal": ["cvae.goal_key=null"], "no_pessimism": ["ablation.no_pessimism=true"]}
#: UOF settings tried beyond the paper's (``--variants``), on any task and dataset; their runs carry the name as ablations do
VARIANTS = {"latent05": ["model_env.latent_bound=0.5"]}
SETTINGS = {**ABLATIONS, **VARIANTS}
LABELS = {"uof": "UOF (ours)", "sac_her": "SAC + HER", "bc": "BC", "uof-no_cvae": "UOF, no CVAE", "uof-cvae_no_goal": "UOF, CVAE without goal",
          "uof-no_pessimism": "UOF, no pessimistic termination", "uof-latent05": "UOF, latent box ±0.5"}
#: the paper's Table II (task 2, D4RL-free: their own data from UOF agents) and its task-1 statement
PAPER = {"blockstack3": {"uof": [0.90, 0.71, 0.41, 0.93, 0.81, 0.46], "sac_her": [0.33, 0.03, 0.0, 0.20, 0.01, 0.0], "bc": [0.99, 0.50, 0.0, 0.99, 0.20, 0.0]}}


def budget(algo: str, frames: int) -> list[str]:
    if algo == "bc":
        return ["train.total_updates=20000", "eval.every_updates=4000"]
    extra = ["algo.utd_ratio=0.1"] if algo == "sac_her" else []
    return [f"train.total_frames={frames}", f"eval.every_frames={frames // 5}", *extra]


#: the model-env agents' budget the runs were first made at; a run at another budget says so in its name (``uof.f200k-...``)
DEFAULT_FRAMES = 40_000


def algo_key(algo: str, frames: int = DEFAULT_FRAMES) -> str:
    """The agent's name in run names and the report's groups: the algorithm, with its budget where it is not the default.

    Examples:
        >>> algo_key("uof"), algo_key("uof", 200_000), algo_key("bc", 200_000), algo_key("uof", 62_500)
        ('uof', 'uof.f200k', 'bc', 'uof.f62500')
    """
    if algo == "bc" or frames == DEFAULT_FRAMES:
        return algo
    return f"{algo}.f{frames // 1000}k" if frames % 1000 == 0 else f"{algo}.f{frames}"  # never two budgets under one name


def key_parts(key: str) -> tuple[str, str, str]:
    """``(algorithm, budget, ablation)`` of an agent key (:func:`algo_key`, with an ablation suffix); ``""`` where absent.

    Examples:
        >>> key_parts("uof"), key_parts("uof.f200k-no_cvae"), key_parts("sac_her")
        (('uof', '', ''), ('uof', '200k', 'no_cvae'), ('sac_her', '', ''))
    """
    agent, _, ablation = key.partition("-")
    algo, _, budget = agent.partition(".f")
    return algo, budget, ablation


def _unbudgeted(key: str) -> str:
    """The key without its budget (``uof.f200k-no_cvae`` -> ``uof-no_cvae``): the name :data:`LABELS` knows."""
    algo, _, ablation = key_parts(key)
    return f"{algo}-{ablation}" if ablation else algo


def label(key: str) -> str:
    """The report's row label for an agent key (:func:`algo_key`, with an ablation suffix).

    Examples:
        >>> label("uof"), label("uof.f200k"), label("uof.f200k-no_cvae"), label("sac_her-no_cvae")
        ('UOF (ours)', 'UOF (ours), 200k frames', 'UOF, no CVAE, 200k frames', 'sac_her-no_cvae')
    """
    name, budget = _unbudgeted(key), key_parts(key)[1]
    if name not in LABELS:
        return key
    return LABELS[name] + (f", {budget} frames" if budget else "")


def _is_uof(key: str) -> bool:
    """UOF at any budget, not an ablation (the agents the last-goal verdicts and option-usage figures are about)."""
    algo, _, ablation = key_parts(key)
    return algo == "uof" and not ablation


def run_name(task: str, dataset: str, algo: str, seed: int, ablation: str | None = None, frames: int = DEFAULT_FRAMES) -> str:
    """Examples:
        >>> run_name("blockstack2", "medium", "uof", 4), run_name("blockstack2", "medium", "uof", 4, frames=200_000)
        ('uof-blockstack2-medium-seed4', 'uof.f200k-blockstack2-medium-seed4')
    """
    return f"{algo_key(algo, frames)}-{task}-{dataset}" + (f"-{ablation}" if ablation else "") + f"-seed{seed}"


def split_run_name(name: str) -> tuple[str, str, str]:
    """``(task, dataset, agent key)`` of a run directory's name (:func:`run_name`): the key with its ablation or variant.

    Examples:
        >>> split_run_name("uof.f200k-blockstack2-medium-expert-no_cvae-seed4")
        ('blockstack2', 'medium-expert', 'uof.f200k-no_cvae')
        >>> split_run_name("uof-blockstack2-uof-epoch50-latent05-seed7"), split_run_name("bc-blockstack3-medium-expert-seed5")
        (('blockstack2', 'uof-epoch50', 'uof-latent05'), ('blockstack3', 'medium-expert', 'bc'))
    """
    algo, rest = name.rsplit("-seed", 1)[0].split("-", 1)
    task, _, tail = rest.partition("-")
    setting = next((a for a in SETTINGS if tail.endswith("-" + a)), None)
    dataset = tail[: -len(setting) - 1] if setting else tail
    return task, dataset, algo + (f"-{setting}" if setting else "")


def dataset_spec(task: str, dataset: str, transitions: int) -> str:
    """What a run's ``dataset=`` gets for a dataset name of ``--datasets``: a scripted level as it is; ``uof-epoch20`` (any
    ``uof-*``: the shipped UOF policy ``<task>-uof-epoch20``, the paper's data route) the file that policy collects with the
    ``medium`` level's noise (``SCRIPT_LEVELS["medium"]``: only the controller differs from the scripted ``medium`` data),
    collected and cached on first use."""
    if not dataset.startswith("uof-"):
        return dataset
    from torchrl_offhrl.data.stacking import SCRIPT_LEVELS
    from torchrl_offhrl.recipes.uof_policies import uof_route_dataset

    random_prob, noise_std = SCRIPT_LEVELS["medium"]
    return str(uof_route_dataset(task, f"{task}-{dataset}", transitions, random_prob=random_prob, noise_std=noise_std))


def run(tasks, datasets, algos, seeds, ablations: list[str] | None, frames: int, transitions: int, variants: list[str] | None = None) -> None:
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    jobs = [(t, d, a, s, None) for t in tasks for d in datasets for s in seeds for a in algos]
    if ablations:
        jobs += [("blockstack2", "medium-expert", "uof", s, ab) for ab in ablations for s in seeds]
    jobs += [(t, d, "uof", s, v) for v in variants or [] for t in tasks for d in datasets for s in seeds]
    for task, dataset, algo, seed, ab in jobs:
        name = run_name(task, dataset, algo, seed, ab, frames)
        over = [f"algo={algo}", f"env={task}", f"dataset={dataset_spec(task, dataset, transitions)}", f"num_transitions={transitions}", f"seed={seed}", f"run_dir={BASE / name}",
                "torch_threads=1", *budget(algo, frames), *(SETTINGS[ab] if ab else [])]
        s = train(to_plain(compose("offline_train", over)))
        archive()  # kept in docs/results/blockstack/runs/ at once: outputs/ does not outlive the machine
        print(f"{name}: final success per goal {s['final'].get('success_per_goal')}", flush=True)


def _sac_her_note(groups: dict) -> str:
    """Which bootstrapping SAC + HER's archived runs used (``algo.terminal_on_success``; absent in a config: true, the old behaviour)."""
    runs = sorted(d for g in groups.values() for algo, ds in g.items() if algo.startswith("sac_her") for d in ds)
    if not runs:
        return ""
    old = [d.name for d in runs if json.loads((d / "config.json").read_text())["algo"].get("terminal_on_success", True)]
    why = ("`algo.terminal_on_success=true` (a met sub-goal stopped the critic's bootstrap, so SAC's entropy bonus made reaching it the "
           "worst action; `blockstack/sac_her_notes.md`)")
    if old:
        return (f"**SAC + HER's runs {', '.join(old)} predate the fix of its collapse**: they ran with {why}. With Stable-Baselines3's "
                "bootstrapping, now the default, its untrained success is kept.")
    return (f"SAC + HER's runs use Stable-Baselines3's bootstrapping (`algo.terminal_on_success=false`, the default since the fix of its "
            f"collapse); the rows of this page before that fix ran with {why} and ended at 0 success on every goal.")


def archive() -> list[Path]:
    """Archive every finished run under ``outputs/results/blockstack/`` to ``docs/results/blockstack/runs/<run>/``."""
    from torchrl_offhrl.recipes.report import archive_runs

    return archive_runs(BASE, ARCHIVE, extra=("option_usage.pt",))


def _legacy() -> dict:
    path = OUT / "blockstack" / "legacy.json"
    return json.loads(path.read_text()) if path.is_file() else {"sections": {}, "runs": {}}


def _fmt(xs) -> str:
    """Success rates over seeds: their interquartile mean with its 95% bootstrap confidence interval (one value as it is).

    Examples:
        >>> _fmt([1.0, 1.0, 1.0]), _fmt([0.5]), _fmt([float("nan")])
        ('1.00 [1.00, 1.00]', '0.50', 'n/a')
    """
    from torchrl_offhrl.stats import iqm_ci

    xs = [x for x in xs if x == x]
    if not xs:
        return "n/a"
    if len(xs) == 1:
        return f"{xs[0]:.2f}"
    m, lo, hi = iqm_ci(xs)
    return f"{m:.2f} [{lo:.2f}, {hi:.2f}]"


def report() -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from torchrl_offhrl.recipes.report import plot_goal_success

    archive()
    runs = sorted(d for d in ARCHIVE.glob("*-seed*") if (d / "summary.json").is_file())
    legacy = _legacy()
    if not runs and not legacy["sections"]:
        raise SystemExit(f"no finished runs under {BASE} or {ARCHIVE}: run `offhrl results blockstack run` first")
    fig_dir = OUT / "blockstack"
    fig_dir.mkdir(parents=True, exist_ok=True)
    groups: dict[tuple[str, str], dict[str, list[Path]]] = {}
    for d in runs:
        task, dataset, key = split_run_name(d.name)
        groups.setdefault((task, dataset), {}).setdefault(key, []).append(d)
    lines = ["# Offline UOF on block stacking: per-goal success", "",
             "Made by `offhrl results blockstack report` from the finished runs (`offhrl results blockstack run` "
             "makes them under `outputs/results/blockstack/` and archives each to `docs/results/blockstack/runs/<run>/`). Groups marked "
             "*(earlier page)* are printed as an earlier version of this page gave them: their run directories were lost between sessions "
             "(`docs/results/blockstack/legacy.json`).", "", __doc__.split("Budgets (CPU):")[1].split("``--ablations``")[0].strip(), "",
             "Success: the share of an evaluation's episodes of that goal whose success flags equalled the goal at some step (the "
             "env's high-level reward 0), for every agent the same test; interquartile mean over seeds with its 95% bootstrap confidence interval [lower, upper] (groups of the earlier page: mean ± std), per-seed values at the end. *Final*: the last evaluation; *best*: "
             "the best mean success over the evaluations after training began, per seed (never the reported result). *Data*: the "
             "behaviour data's own per-goal success at horizon 25.", ""]
    if note := _sac_her_note(groups):
        lines += [note, ""]
    earlier = {tuple(x.strip() for x in key.split(",")): section for key, section in legacy["sections"].items()}
    for (task, dataset) in sorted(set(groups) | set(earlier)):
        if (task, dataset) in earlier:  # as the earlier page gave it (its runs were lost), less what was rerun since
            rerun = {label(k): len(ds) for k, ds in groups.get((task, dataset), {}).items()}
            if left := _earlier_left(earlier[(task, dataset)], rerun, figures=(task, dataset) not in groups):
                lines += [left, ""]
        if (task, dataset) not in groups:
            continue
        algos = groups[(task, dataset)]
        meta = _dataset_success(algos)
        lines += [f"## {task}, {dataset}", "", "| agent | seeds | final, horizon 25 | final, horizon 50 | best (mean over goals) |", "|---|---|---|---|---|"]
        if meta:
            lines.append(f"| data (behaviour) | | {' / '.join(f'{x:.2f}' for x in meta)} | | |")
        evals_of = {algo: [json.loads((d / "evals.json").read_text()) for d in ds] for algo, ds in algos.items()}  # read once per group
        for algo, ds in sorted(algos.items(), key=lambda kv: (list(LABELS).index(_unbudgeted(kv[0])) if _unbudgeted(kv[0]) in LABELS else 99, kv[0])):
            evs = evals_of[algo]
            last = [e[-1] for e in evs]
            n = len(last[0]["success_per_goal"])
            h50 = next((k for k in last[0] if k.startswith("success_per_goal_h")), None)
            c25 = " / ".join(_fmt([r["success_per_goal"][k] for r in last]) for k in range(n))
            c50 = " / ".join(_fmt([r[h50][k] for r in last]) for k in range(n)) if h50 else "n/a"
            best = _fmt([max(e2["success_rate"] for e2 in e if e2.get("step", e2["frames"]) > 0) for e in evs])
            lines.append(f"| {label(algo)} | {len(ds)} | {c25} | {c50} | {best} |")
        lines.append("")
        if verdict := _last_goal_verdict(evals_of):
            lines += [verdict, ""]
        fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.3), sharey=True, squeeze=False)
        for algo in sorted(algos):
            if algo == "bc":
                continue  # another x-axis (gradient steps); its final numbers are in the table
            plot_goal_success(evals_of[algo], None, label=label(algo), axes=axes[0], xlabel="model-env frames")
        if axes[0][0].get_legend_handles_labels()[0]:  # BC alone draws no curve
            axes[0][0].legend(fontsize=7)
        fig.suptitle(f"{task}, {dataset}: success per goal (horizon 25), mean ± std over seeds", fontsize=9)
        fig.tight_layout()
        png = fig_dir / f"success_{task}_{dataset}.png"
        fig.savefig(png, dpi=110)
        plt.close(fig)
        lines += [f"![success per goal]({png.relative_to(OUT)})", ""]
        for key in sorted(filter(_is_uof, algos)):  # UOF at each budget (not the ablations)
            usage = [torch.load(d / "option_usage.pt", weights_only=True) for d in algos[key] if (d / "option_usage.pt").is_file()]
            if not usage:
                continue
            from torchrl_offhrl.agents.uof import plot_goal_option_usage

            t = min(u.shape[1] for u in usage)
            mean = torch.stack([u[:, :t] for u in usage]).mean(0)
            budget = key_parts(key)[1]
            png = fig_dir / f"option_usage_{task}_{dataset}{f'_{budget}' if budget else ''}.png"
            who = label(key).replace(" (ours)", "")
            plot_goal_option_usage(mean, png, title=f"{who} option usage per goal at the final evaluation, {task} {dataset} "
                                                     f"(mean over {len(usage)} seed{'s' if len(usage) > 1 else ''})")
            at = f", the runs at {budget} model frames" if budget else ""
            lines += [f"Which option (sub-goal) UOF's high level runs at each step of the final evaluation, per goal (the paper's "
                      f"Figs. 6-7){at}:", "", f"![option usage]({png.relative_to(OUT)})", ""]
    lines += ["## The paper's numbers (measured on its own data from partially trained UOF agents, not on ours)", "",
              "| task | agent | success per goal |", "|---|---|---|"]
    for task, rows in PAPER.items():
        for algo, xs in rows.items():
            lines.append(f"| {task} | {LABELS[algo]} | {' / '.join(f'{x:.2f}' for x in xs)} |")
    lines += ["| blockstack2, medium-expert | UOF (ours) | about 0.8 on the final goal (iii) |", ""]
    lines += _against_paper(groups)
    lines += ["Per run (final success per goal at horizon 25):", ""]
    per_run = {}
    for d in runs:
        e = json.loads((d / "evals.json").read_text())[-1]
        per_run[d.name] = (f"{' / '.join(f'{x:.2f}' for x in e['success_per_goal'])} at {e.get('step', e['frames'])} "
                           f"{json.loads((d / 'summary.json').read_text()).get('unit', 'frames')}")
    for name, line in legacy["runs"].items():  # the lost runs of the earlier page, unless rerun since
        if name not in per_run:
            per_run[name] = f"{line} (earlier page)"
    lines += [f"- `{name}`: {line}" for name, line in sorted(per_run.items())]
    text = "\n".join(lines) + "\n"
    (OUT / "block_stacking.md").write_text(text)
    for d in runs:  # keep each run's own figures next to the report (while its run directory is here)
        for f in ("success.png",):
            if (BASE / d.name / f).is_file():
                shutil.copyfile(BASE / d.name / f, fig_dir / f"{d.name}_{f}")
    return text


def _earlier_left(section: str, rerun: dict[str, int], figures: bool = True) -> str | None:
    """An earlier page's section (``legacy.json``) less its agent rows rerun since on as many seeds or more (``rerun``:
    label -> seeds of the archived groups of the same task and dataset, which the section after it prints), marked
    *(earlier page)*; its figures only with ``figures`` (the file names are the new runs' once they exist); None when
    no agent row is left.

    Examples:
        >>> s = "## t, d\\n\\n| agent | seeds |\\n|---|---|\\n| data (behaviour) | |\\n| BC | 3 |\\n| UOF (ours) | 3 |\\n\\n![f](x.png)"
        >>> print(_earlier_left(s, {"BC": 5, "UOF (ours)": 1}, figures=False))
        ## t, d *(earlier page)*
        <BLANKLINE>
        | agent | seeds |
        |---|---|
        | data (behaviour) | |
        | UOF (ours) | 3 |
        >>> _earlier_left(s, {"BC": 3, "UOF (ours)": 5}) is None
        True
    """
    head, _, body = section.partition("\n")
    keep, agents = [], 0
    for line in body.rstrip().split("\n"):
        cell = line.split("|")[1].strip() if line.startswith("| ") else None
        if cell is not None and cell not in ("agent", "data (behaviour)"):
            seeds = line.split("|")[2].strip()
            if cell in rerun and rerun[cell] >= (int(seeds) if seeds.isdigit() else 1):
                continue
            agents += 1
        if not figures and (line.startswith("![") or line.startswith("Which option")):
            continue
        keep.append(line)
    if not agents:
        return None
    while keep and not keep[-1].strip():
        keep.pop()
    out = "\n".join(keep)
    while "\n\n\n" in out:
        out = out.replace("\n\n\n", "\n\n")
    return f"{head} *(earlier page)*\n{out}"


def _against_paper(groups: dict) -> list[str]:
    """The paper's Table II beside this page's runs of the same task (``blockstack3``, medium-expert: the scripted data
    closest to its 200-epoch UOF data), goal by goal: the final success at horizon 25, IQM over seeds."""
    from torchrl_offhrl.stats import iqm_ci

    out = []
    for task, rows in PAPER.items():
        ours = groups.get((task, "medium-expert"), {})
        if not ours:
            continue
        out += [f"Table II against this page's {task} medium-expert runs (final success at horizon 25; ours: IQM over the seeds, "
                "on scripted data; the paper's: its own data from a 200-epoch UOF agent, seeds not stated):", "",
                "| agent | seeds | " + " | ".join(f"goal {k + 1}" for k in range(len(next(iter(rows.values()))))) + " |",
                "|---|---|" + "---|" * len(next(iter(rows.values())))]
        for key in sorted(ours, key=lambda k: (list(LABELS).index(_unbudgeted(k)) if _unbudgeted(k) in LABELS else 99, k)):
            algo, _, ablation = key_parts(key)
            if ablation or algo not in rows:
                continue
            last = [json.loads((d / "evals.json").read_text())[-1]["success_per_goal"] for d in ours[key]]
            cells = [f"{iqm_ci([r[k] for r in last])[0]:.2f} (paper {rows[algo][k]:.2f})" for k in range(len(rows[algo]))]
            out.append(f"| {label(key)} | {len(last)} | " + " | ".join(cells) + " |")
        out += ["", "Why the order of the agents differs from the paper's on our data, measured: `blockstack/uof_notes.md` (the "
                "budget, BC's ceiling on scripted data, the paper's data route, the model's optimism, the low level handed BC's "
                "sub-goals, DIOL's schedule) and `blockstack/sac_her_notes.md` (SAC + HER).", ""]
    return out


def last_goal_comparison(uof: list[float], bc: list[float], name: str = "UOF") -> str:
    """UOF against BC on a task's last goal (final success at horizon 25, one value per seed): both IQMs with their 95%
    bootstrap CIs and what they show (issue 39 asks for UOF >= BC with CIs that do not overlap). With 3 seeds the IQM
    trims nothing: it is the mean (0.1 / 3 = 0.03 and 1.0 / 3 = 0.33 below).

    Examples:
        >>> last_goal_comparison([0.0, 0.1, 0.0], [0.3, 0.6, 0.1])
        'Last goal, final success at horizon 25: UOF 0.03 [0.00, 0.10] against BC 0.33 [0.10, 0.60]: the CIs overlap, no difference shown.'
        >>> last_goal_comparison([0.8, 0.9, 0.7], [0.0, 0.1, 0.0]).split(": ")[-1]
        'UOF above BC, the CIs apart.'
    """
    from torchrl_offhrl.stats import iqm_ci

    (mu, lu, hu), (mb, lb, hb) = iqm_ci(uof), iqm_ci(bc)
    verdict = (f"{name} above BC, the CIs apart." if lu > hb else f"BC above {name}, the CIs apart." if lb > hu
               else "the CIs overlap, no difference shown.")
    return (f"Last goal, final success at horizon 25: {name} {mu:.2f} [{lu:.2f}, {hu:.2f}] against BC {mb:.2f} [{lb:.2f}, {hb:.2f}]: "
            f"{verdict}")


def _last_goal_verdict(evals_of: dict) -> str | None:
    """:func:`last_goal_comparison` for a (task, dataset) group (``algo -> each seed's evaluations``): one line per UOF
    budget (``uof``, ``uof.f200k``, ...) with 2+ seeds, against BC's 2+ seeds; None when there is none."""
    bc = evals_of.get("bc", [])
    uofs = sorted(k for k in evals_of if _is_uof(k) and len(evals_of[k]) >= 2)
    if len(bc) < 2 or not uofs:
        return None
    last = lambda evs: [e[-1]["success_per_goal"][-1] for e in evs]  # noqa: E731
    return "\n\n".join(last_goal_comparison(last(evals_of[k]), last(bc), name=label(k).replace(" (ours)", "")) for k in uofs)


def _dataset_success(algos: dict) -> list[float] | None:
    """The behaviour data's per-goal success, from any run's dataset metadata (``summary.json``)."""
    for ds in algos.values():
        for d in ds:
            succ = json.loads((d / "summary.json").read_text()).get("behaviour_success_per_goal")
            if succ:
                return [float("nan") if x is None else x for x in succ]
    return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results blockstack", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--tasks", nargs="+", default=["blockstack2"])
    r.add_argument("--datasets", nargs="+", default=["medium-expert", "medium"],
                   help="scripted levels (medium, expert, medium-expert) or the paper's data route: uof-epoch20 | uof-epoch50 (collected "
                        "by the shipped UOF policy <task>-uof-epochN with the medium level's noise, cached)")
    r.add_argument("--algos", nargs="+", default=["uof", "sac_her", "bc"])
    r.add_argument("--seeds", nargs="+", type=int, default=[4, 5, 6, 7, 8], help="evaluation seeds (default 4-8: five, as the results)")
    r.add_argument("--ablations", nargs="*", choices=sorted(ABLATIONS), default=None,
                   help="UOF ablations on task 1 medium-expert (no names: all three)")
    r.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=None,
                   help="UOF with a setting beyond the paper's on every --tasks x --datasets x --seeds (latent05: the latent box "
                        "±0.5 instead of ±2, docs/results/blockstack/uof_notes.md row 14)")
    r.add_argument("--no-main", action="store_true", help="only the ablations and variants, not the --algos runs")
    r.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                   help="model-env frames of UOF and SAC + HER; runs at another budget than 40k carry it in their names (uof.f200k-...)")
    r.add_argument("--transitions", type=int, default=100_000)
    sub.add_parser("report")
    a = p.parse_args(argv)
    if a.cmd == "run":
        ablations = None if a.ablations is None else (a.ablations or sorted(ABLATIONS))
        run(a.tasks, a.datasets, [] if a.no_main else a.algos, a.seeds, ablations, a.frames, a.transitions, a.variants)
    else:
        print(report())
    return 0

