"""Does the demo's method work on any machine? The demo setting on many dataset seeds.

    offhrl results robustness run VARIANT --dataset-seeds 4 5 6 7 8 9 10 11 12 13   # resumable
    offhrl results robustness table [VARIANT ...]      # -> docs/results/demo_robustness.md
    offhrl results robustness list

Data generated on another CPU differs in its floating-point details; a new
``dataset_seed`` (its own 100k transitions of the shipped hopper-medium
policy, its own ensemble and CVAE fits) simulates that. Each variant is a
list of hydra overrides of ``configs/demo.yaml``; agent seed 0 per dataset
seed unless ``--agent-seeds`` asks for others (runs ``d<seed>a<agent>``). Dataset seeds 1-3 are for choosing (tuning); 4 and up for
reporting. Run directories: ``outputs/demo_robustness/<variant>/d<seed>``; what the
table reads (config, evaluations, summaries) is archived in the repo under
``docs/results/demo_robustness_runs/<variant>/d<seed>`` as each run finishes (the cache, ``$TORCHRL_OFFHRL_CACHE``, keeps the datasets and models: a
second variant on the same dataset seed costs only its agent's training).
Two runs side by side on a 2-core machine (two dataset seeds at once): give each ``OMP_NUM_THREADS=1``.
The model fits run at ``fit_threads`` torch threads (default: torch's count, all cores; ``torch_threads`` applies after
them; ``OMP_NUM_THREADS=1`` sets both), and two fits at two threads each on two cores ran 2-5x slower than at one thread each (ensemble steps: 6-17 against 17-35
per second beside another job, measured 2026-12-03): a dataset seed's fits took 20-45 minutes instead of a few.

The table scores, per dataset seed, the behaviour data, the untrained agent
(the CVAE decoder's mean action), the last policy, the policy chosen by
offline policy selection (what the demo returns), the best evaluation and the
mean of the last five, and counts the seeds where the returned policy beats
both its untrained start and the data.
"""
from __future__ import annotations

import argparse
import json

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
OUT = ROOT / "outputs" / "demo_robustness"
DOC = ROOT / "docs" / "results" / "demo_robustness.md"
#: what the table reads: each finished run's config, evals, summary and demo summary (``archive_run``), kept in the repo
ARCHIVE = ROOT / "docs" / "results" / "demo_robustness_runs"

#: name -> (what it changes, overrides of configs/demo.yaml)
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "shipped": ("the demo as first shipped after issue 37's choices (configs/demo.yaml with its ensemble fitted 10k steps): 100-step "
                "model episodes branched from any dataset state, the last policy", []),
    "horizon1000_lcb": ("the demo before issue 37: 1000-step model episodes from the data's start states; returned policy by model_lcb",
                        ["model_env.reset_states=initial", "model_env.horizon=1000", "selection.criterion=model_lcb"]),
    "branch": ("the shipped demo with the returned policy chosen by model_lcb", ["selection.criterion=model_lcb"]),
    "bound1": ("horizon1000_lcb with the latent box [-1, 1] instead of [-2, 2] (a trust region around the CVAE prior's mode)",
               ["model_env.reset_states=initial", "model_env.horizon=1000", "selection.criterion=model_lcb", "model_env.latent_bound=1.0"]),
    "branch_bound1": ("branch with the latent box [-1, 1]", ["selection.criterion=model_lcb", "model_env.latent_bound=1.0"]),
    "one_option": ("the shipped demo with one option (MOC's machinery without options)", ["algo.num_options=1"]),
    "pess_q999": ("the shipped demo with the P-MDP threshold at the 99.9% quantile of the data's discrepancies, not 1.08 x their max",
                  ["model_env.pessimism={quantile: 0.999, penalty: 20.0}"]),
    "ema": ("the shipped demo returning the Polyak average of the policy's weights (algo.policy_ema=0.1 per 2048-frame batch)",
            ["algo.policy_ema=0.1"]),
    "pess_q99": ("the shipped demo with the P-MDP threshold at the 99% quantile of the data's discrepancies, not 1.08 x their max",
                 ["model_env.pessimism={quantile: 0.99, penalty: 20.0}"]),
    "mopo2": ("the shipped demo with MOPO's soft pessimism: every model step pays 2 x the members' discrepancy",
              ["model_env.reward_penalty=2.0"]),
    "bound15": ("the shipped demo with the latent box [-1.5, 1.5] instead of [-2, 2] (a looser trust region than bound1's)",
                ["model_env.latent_bound=1.5"]),
    "h25": ("the shipped demo with model episodes of 25 steps instead of 100 (less compounding model error per rollout)",
            ["model_env.horizon=25"]),
    "mopo5": ("the shipped demo with MOPO's soft pessimism: every model step pays 5 x the members' discrepancy",
              ["model_env.reward_penalty=5.0"]),
    "gamma998": ("the shipped demo with the discount 0.998 instead of 0.99 (an effective horizon of ~500 steps, not ~100: "
                 "under 0.99 a gait that falls at step 350 is worth as much as one that runs 1,000 steps)",
                 ["algo.gamma=0.998"]),
    "std037": ("the shipped demo with the intra-option policies' initial std exp(-1) = 0.37 instead of 1 in the latent space "
               "(algo.init_log_std=-1): with std 1 the policy MOC trains is the CVAE prior's spread around its mean, and the std "
               "stays at 1.00 over the demo's budget", ["algo.init_log_std=-1.0"]),
    "machine2": ("the shipped demo rerun on another machine of the same kind (2-core AMD EPYC, a fresh clone): the same datasets "
                 "bit for bit, the models fitted anew (their fits differ in floating point), so what the machine alone changes; "
                 "the pair of every variant measured on that machine", []),
    "mb64": ("the shipped demo with MOC's minibatches of 64 (the official code's) instead of 256: 320 policy and critic steps per "
             "2048-frame batch instead of 80; the updates take ~23 s of the demo's ~3 min of training, so 4x as many fit its budget",
             ["algo.minibatch_size=64"]),
    "stdlr": ("the shipped demo with the intra-option log-stds learning at 1e-3 instead of the policy's 1e-4 "
              "(algo.log_std_lr=1e-3): at 1e-4 they cannot move over the demo's ~3,200 annealed steps, so PPO trains a "
              "policy as wide as the prior; here the std can shrink where the return asks it to",
              ["algo.log_std_lr=1.0e-3"]),
    "stdsched": ("the shipped demo with the intra-option std on a schedule instead of learned (algo.final_log_std=-1): "
                 "exp(0) = 1 at the start (where the shipped runs find their gaits), exp(-1) = 0.37 at the end (where std037's "
                 "runs kept the gaits they found)", ["algo.final_log_std=-1.0"]),
    "batch4096": ("the shipped demo with batches of 4,096 frames (128 model envs x 32 steps) instead of 2,048 and minibatches of "
                  "512 instead of 256 over twice the frames (163,840): the same 40 iterations and 80 updates per batch, each "
                  "gradient from twice the data (lower-variance PPO steps)",
                  ["algo.frames_per_batch=4096", "collector.num_envs=128", "algo.minibatch_size=512", "train.total_frames=163840",
                   "eval.every_frames=20480"]),
    "prior1": ("the shipped demo with a soft trust region around the CVAE prior's mode (algo.prior_coef=1): every option's "
               "mode latent action pays 0.5 x its squared norm in the intra-option loss, against advantages normalised to unit "
               "spread; the latent actions' norm grew from 0.4-0.7 at the gaits to 0.8-1.1 after the collapses (row 2)",
               ["algo.prior_coef=1.0"]),
    "prior01": ("prior1 with a tenth of the coefficient (algo.prior_coef=0.1): at 1 the mode actions stay at the prior's mode "
                "and the policy at its untrained score", ["algo.prior_coef=0.1"]),
    "prior003": ("prior1 with algo.prior_coef=0.03", ["algo.prior_coef=0.03"]),
    "clip01": ("the shipped demo with PPO's own trust region halved: the intra-option ratio clipped at 0.1 instead of the paper's "
               "0.2 (algo.clip_epsilon=0.1; the env group's PPO value on Hopper), so that no batch moves the policy far from the one "
               "that collected it", ["algo.clip_epsilon=0.1"]),
    "models30k": ("the shipped demo with the ensemble fitted 30k steps instead of 10k (a model with less error for the policy to "
                  "exploit: row 15 of the notes found the collapsing policies exploiting the dynamics' error); the demo's setting "
                  "from 0.2.0 on", ["ensemble.fit.max_steps=30000"]),
}

#: the variant configs/demo.yaml was until the offline rules replaced it (2026-12-06; LEGACY below): the demo printed the
#: count of its evaluation runs (recipes.demo.CHECKED) until then
SHIPPED = "models30k"
#: the variants run while configs/demo.yaml fitted its ensemble 10k steps: their reruns add ``FIT10K`` to stay what they
#: were. A variant added later changes today's demo.yaml and does not belong here.
FIT10K = ["ensemble.fit.max_steps=10000"]
ON_FIT10K = frozenset(VARIANTS) - {"models30k"}


#: configs/demo.yaml as it was before the offline rules (2026-12-06): every variant above was run on it. The paper preset
#: (its pessimism table, fixed fit budgets, the last policy, no guard) plus the demo's own branched 100-step episodes and
#: 30k/10k-step fits; a test checks that these overrides give the archived runs' configs
LEGACY = ["preset=paper", "model_env.horizon=100", "model_env.reset_states=any", "ensemble.fit.max_steps=30000", "cvae.fit.lr=1e-3",
          "cvae.fit.max_steps=10000"]


def overrides(variant: str) -> list[str]:
    """The hydra overrides of configs/demo.yaml that make ``variant`` (what its archived runs ran)."""
    return [*LEGACY, *(FIT10K if variant in ON_FIT10K else []), *VARIANTS[variant][1]]


#: variant -> the baselines it is compared with run for run (same dataset and agent seeds): the paired
#: block of the table, on the runs both have. The earlier variants' pairs (the shipped demo's archived runs) are in the notes.
PAIRED = {**{v: ("machine2",) for v in ("stdlr", "mb64", "stdsched", "batch4096", "prior1", "prior01", "prior003", "clip01")},
          # the evaluation seeds' pair: the earlier shipped demo's runs (the first machine: the same datasets, other model fits)
          "models30k": ("machine2", "shipped")}


def run_name(d: int, a: int = 0) -> str:
    """The folder of dataset seed ``d`` and agent seed ``a``: ``d<d>`` for the demo's agent seed 0, else ``d<d>a<a>``."""
    return f"d{d}" if a == 0 else f"d{d}a{a}"


def parse_name(name: str) -> tuple[int, int]:
    """``(dataset seed, agent seed)`` of a run folder named by :func:`run_name`."""
    d, _, a = name[1:].partition("a")
    return int(d), int(a or 0)


def run(variant: str, seeds: list[int], agent_seeds: list[int] = (0,)) -> None:
    from torchrl_offhrl.recipes.demo import run_demo

    ov = overrides(variant)
    # every evaluation's policy kept (snapshot-<frames>.pt): other selection criteria can be scored afterwards
    over = dict(o.split("=", 1) for o in ov if "=" in o)
    every, total = int(over.get("eval.every_frames", 10240)), int(over.get("train.total_frames", 81920))
    snaps = f"train.snapshot_frames=[{','.join(str(every * k) for k in range(1, total // every + 1))}]"
    for d in seeds:
        for a in agent_seeds:
            name = run_name(d, a)
            out = OUT / variant / name
            if (out / "demo_summary.json").is_file():
                print(f"{out}: done")
                if not (ARCHIVE / variant / name / "demo_summary.json").is_file():
                    archive(variant, name)
                continue
            run_demo([*ov, f"dataset_seed={d}", f"seed={a}", f"run_dir={out}", snaps], progress=False)
            archive(variant, name)


def archive(variant: str, name: str) -> None:
    from torchrl_offhrl.recipes.report import archive_run

    archive_run(OUT / variant / name, ARCHIVE / variant / name, extra=("demo_summary.json",))


def _score(rec):
    return None if rec is None else rec.get("normalized_d4rl")


def runs_of(variant: str) -> list[tuple[tuple[int, int], list[dict], dict]]:
    """``((dataset seed, agent seed), evaluation records, demo summary)`` of each archived run of ``variant``, by seeds."""
    out = []
    for path in sorted((ARCHIVE / variant).glob("d*/demo_summary.json"), key=lambda p: parse_name(p.parent.name)):
        out.append((parse_name(path.parent.name), json.loads((path.parent / "evals.json").read_text()), json.loads(path.read_text())))
    return out


def label(seeds: tuple[int, int]) -> str:
    """A run's name in the tables: its dataset seed, and its agent seed where it is not the demo's 0."""
    return str(seeds[0]) if seeds[1] == 0 else f"{seeds[0]} (agent {seeds[1]})"


def beats_both(score: float, s: dict) -> bool:
    """A policy's score above both the run's untrained start and its behaviour data."""
    return score > _score(s["initial"]) and score > s["behaviour_normalized_d4rl"]


def rows_of(variant: str) -> list[dict]:
    rows = []
    for (d, a), evals, s in runs_of(variant):
        trained = [e for e in evals if e["frames"] > 0]
        ret = s.get("selected") or s["final"]  # the returned policy's record
        rows.append({
            "dataset_seed": d, "agent_seed": a, "behaviour": s["behaviour_normalized_d4rl"], "untrained": _score(s.get("initial")),
            "last": _score(s["final"]), "selected": _score(ret), "selected_frames": ret["frames"], "best": max(_score(e) for e in trained),
            "last5": sum(_score(e) for e in trained[-5:]) / len(trained[-5:]), "beats_both": beats_both(_score(ret), s),
            "option_kl": ret.get("option_kl"), "option_starts": ret.get("option_starts", ret.get("option_switches")),
        })
    return rows


def criteria_rows(runs: list[tuple[int, list[dict], dict]], names: list[str] | None = None) -> list[str]:
    """Every selection criterion scored afterwards on the same runs: the real score of the evaluation its selector picks.

    ``runs``: ``(key, evaluation records, summary)``; a pick is named ``d<label(key)>``, or by ``names`` where given."""
    from torchrl_offhrl.recipes.selection import CRITERIA, PolicySelector

    class _Index:  # stands for the agent: its "state" is the index of the evaluation being considered
        i = 0

        def state_dict(self):
            return self.i

    if not runs:
        return []
    what = "dataset seed" if names is None else "run"
    names = names or [f"d{label(k)}" for k, _, _ in runs]
    out = [f"| criterion | picked real score per {what} | mean | within 5 of best | beats untrained and data |",
           "|---|---|---|---|---|"]
    for name, key in CRITERIA.items():
        if key is not None and any(key not in e for _, evals, _ in runs for e in evals):
            continue  # a run made before the criterion's record existed
        picks, hits, wins = [], 0, 0
        for _, evals, s in runs:
            sel, agent = PolicySelector(name), _Index()
            for agent.i, e in enumerate(evals):
                sel.consider(e, agent, e["frames"])
            e = evals[sel.selected["index"]]
            best = max(c["normalized_d4rl"] for c in evals if c["frames"] > 0)
            picks.append(e["normalized_d4rl"])
            hits += best - e["normalized_d4rl"] <= 5.0
            wins += beats_both(e["normalized_d4rl"], s)
        out.append(f"| {name} | {', '.join(f'{n}: {x:.1f}' for n, x in zip(names, picks))} | {sum(picks) / len(picks):.1f} | "
                   f"{hits}/{len(picks)} | {wins}/{len(picks)} |")
    return out + [""]


def paired_rows(variant: str, baseline: str, rs: list[dict]) -> list[str]:
    """``variant``'s returned policies against ``baseline``'s on the runs both have (same seeds): per run and the paired change."""
    from torchrl_offhrl.stats import paired_change

    base = {(r["dataset_seed"], r["agent_seed"]): r for r in rows_of(baseline)}
    both = [(r, base[(r["dataset_seed"], r["agent_seed"])]) for r in rs if (r["dataset_seed"], r["agent_seed"]) in base]
    if not both:
        return []
    ch = paired_change([r["selected"] for r, _ in both], [b["selected"] for _, b in both])
    per_run = ", ".join(f"d{label((r['dataset_seed'], r['agent_seed']))}: {b['selected']:.1f} -> {r['selected']:.1f}" for r, b in both)
    return [f"Paired with `{baseline}` on the same {len(both)} runs (returned policy, {baseline} -> {variant}): {per_run}. "
            f"Beats both: {variant} {sum(r['beats_both'] for r, _ in both)}/{len(both)}, {baseline} {sum(b['beats_both'] for _, b in both)}/{len(both)}; "
            f"paired change {ch['mean']:+.1f} [{ch['ci'][0]:+.1f}, {ch['ci'][1]:+.1f}], {ch['up']} of {ch['n']} up.", ""]


def table(variants: list[str]) -> str:
    from torchrl_offhrl.stats import iqm_ci, mean_std

    lines = ["# The demo on many dataset seeds", "",
             "Made by `offhrl results robustness table` from the runs archived in `docs/results/demo_robustness_runs/` by `offhrl results robustness run VARIANT --dataset-seeds ...`.",
             "Each dataset seed generates its own 100k hopper-medium transitions and fits its own ensemble and CVAE (what another "
             "machine's floating point does to the demo); agent seed 0 unless a row names another. D4RL-normalised scores, 30 deterministic real-env "
             "episodes per evaluation. *returned*: the policy the run returns (offline policy "
             "selection, chosen without the real env; the last policy for `last`); *beats both*: returned > untrained and > data. "
             "Dataset seeds 1-3 were used for choices; 4 and up only for reporting.", ""]
    for v in variants:
        rows, runs = rows_of(v), runs_of(v)
        if not rows:
            continue
        for group, pick in (("tuning seeds 1-3", lambda r: r["dataset_seed"] <= 3), ("evaluation seeds 4+", lambda r: r["dataset_seed"] >= 4)):
            rs = [r for r in rows if pick(r)]
            if not rs:
                continue
            lines += [f"## {v}: {VARIANTS[v][0]} ({group})", "",
                      "| dataset seed | data | untrained | returned (frames) | last | best | last-5 mean | beats both | selection within 5 of best | "
                      "options' KL / option starts per episode (returned) |", "|---|---|---|---|---|---|---|---|---|---|"]
            wins = hits = 0
            for r in rs:
                win = r["beats_both"]
                hit = r["best"] - r["selected"] <= 5.0
                wins, hits = wins + win, hits + hit
                opt = "n/a" if r["option_kl"] is None else f"{r['option_kl']:.2f} / {r['option_starts']:.1f}"
                lines.append(f"| {label((r['dataset_seed'], r['agent_seed']))} | {r['behaviour']:.1f} | {r['untrained']:.1f} | {r['selected']:.1f} ({r['selected_frames']}) | "
                             f"{r['last']:.1f} | {r['best']:.1f} | {r['last5']:.1f} | {'yes' if win else 'no'} | {'yes' if hit else 'no'} | {opt} |")
            agg, msd = [], []  # per column: IQM [95% CI] and mean ± std over the runs
            for k in ("behaviour", "untrained", "selected", "last", "best", "last5"):
                values = [r[k] for r in rs]
                (m, lo, hi), (mean, sd, _) = iqm_ci(values), mean_std(values)
                agg.append(f"{m:.1f} [{lo:.1f}, {hi:.1f}]")
                msd.append(f"{mean:.1f} ± {sd:.1f}")
            lines.append(f"| IQM [95% CI] | {' | '.join(agg)} | {wins}/{len(rs)} | {hits}/{len(rs)} | |")
            lines.append("| mean ± std | " + " | ".join(msd) + " | | | |")
            lines.append("")
            for baseline in PAIRED.get(v, ()):
                lines += paired_rows(v, baseline, rs)
            crit = criteria_rows([run for run in runs if pick({"dataset_seed": run[0][0]})])
            if crit:
                lines += [f"Selection criteria compared on the same runs ({group}): the real score of the evaluation each criterion "
                          "picks (after step 0; `selection.criterion`, `torchrl_offhrl.recipes.selection.CRITERIA`).", "", *crit]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results robustness", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("variant", choices=sorted(VARIANTS))
    r.add_argument("--dataset-seeds", type=int, nargs="+", required=True)
    r.add_argument("--agent-seeds", type=int, nargs="+", default=[0], help="agent seeds per dataset seed (default: the demo's 0)")
    t = sub.add_parser("table")
    t.add_argument("variants", nargs="*")
    sub.add_parser("list")
    a = p.parse_args(argv)
    if a.cmd == "run":
        run(a.variant, a.dataset_seeds, a.agent_seeds)
    elif a.cmd == "table":
        text = table(a.variants or list(VARIANTS))
        DOC.write_text(text + "\n")
        print(text)
    else:
        for k, (what, _) in VARIANTS.items():
            print(f"{k:12s}{' (shipped)' if k == SHIPPED else ''} {what}: {' '.join(overrides(k)) or '(none)'}")
    return 0

