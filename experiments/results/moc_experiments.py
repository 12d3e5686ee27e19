"""Small, cached MOC experiments on the demo's setting (100k hopper-medium transitions, demo-size models, 164k frames).

    offhrl results moc-experiments run NAME [NAME ...]     # train the named variants (resumable run dirs)
    offhrl results moc-experiments list                     # the variants
    offhrl results moc-experiments table                    # docs/results/moc_demo_experiments.md from the finished runs

Each variant is a list of hydra overrides of configs/demo.yaml as it was before
issue 13 (LEGACY: CVAE KL weight 0.5, unscaled rewards, 3k-step model fits;
the variants say what they change); the dataset and
the fitted models come from the cache, so a variant costs only its MOC frames.
Rows report the final and the best evaluation separately (10 deterministic
episodes, the training seed's evaluation seeds: these are development runs on
one seed, not results), and the option diagnostics of the last logged batch.
Rows run before the agents switched to fused Adam (``fused_adam``) used torch's
per-tensor Adam: a rerun matches them up to floating-point rounding.
"""
from __future__ import annotations

import argparse
import json

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
OUT = ROOT / "outputs" / "moc_experiments"
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "joint": ("this project's first MOC (every term in every minibatch; 4 options)", ["algo=moc_joint"]),
    "official": ("official MOC switches (configs/algo/moc_official.yaml; 2 options)", ["algo=moc_official"]),
    "official_4opt": ("official, 4 options", ["algo=moc_official", "algo.num_options=4"]),
    "official_rs": ("official, rewards x 0.1 for learning", ["algo=moc_official", "model_env.reward_scale=0.1"]),
    "official_rs_fast_heads": ("official, rewards x 0.1, termination and pi_O lr 1e-3",
                               ["algo=moc_official", "model_env.reward_scale=0.1", "algo.termination_lr=1e-3", "algo.option_lr=1e-3"]),
    "joint_std": ("first MOC, initial intra-option std e^-1 (log_std -1)", ["algo=moc_joint", "algo.init_log_std=-1.0"]),
    "official_std": ("official, initial std e^-1", ["algo=moc_official", "algo.init_log_std=-1.0"]),
    "official_std_rs": ("official, initial std e^-1, rewards x 0.1", ["algo=moc_official", "algo.init_log_std=-1.0", "model_env.reward_scale=0.1"]),
    "ppo": ("PPO (flat), same budget", ["algo=ppo"]),
    "ppo_rs": ("PPO, rewards x 0.1 for learning", ["algo=ppo", "model_env.reward_scale=0.1"]),
}
# the same variants on better-fitted models (20k fitting steps instead of the demo's 3k: the model then
# ends the decoder policy's episodes where the real env does; see experiments/diagnostics/model_episode_ends.py)
FIT20K = ["ensemble.fit.max_steps=20000", "cvae.fit.max_steps=20000"]
for _name in ("joint", "official", "official_std_rs", "ppo"):
    VARIANTS[f"{_name}_fit20k"] = (VARIANTS[_name][0] + "; models fitted 20k steps", VARIANTS[_name][1] + FIT20K)
VARIANTS["ppo_fit20k_500k"] = ("PPO, models fitted 20k steps, 3x the frames (492k)",
                               ["algo=ppo", *FIT20K, "train.total_frames=491520", "eval.every_frames=98304"])
VARIANTS["moc_fit20k_500k"] = ("first MOC, models fitted 20k steps, 3x the frames (492k)",
                               ["algo=moc_joint", *FIT20K, "train.total_frames=491520", "eval.every_frames=98304"])
VARIANTS["ppo_nocvae_fit20k"] = ("PPO in real actions (no CVAE), models fitted 20k steps", ["algo=ppo", "ablation.no_cvae=true", *FIT20K])
# the CVAE's KL weight: at the paper's 0.5 the decoder ignores the latent (posterior collapse: its actions vary
# by ~3% of the data's action std over the latent box), so no latent policy can act differently from it
KL = ["cvae.kl_weight=0.05"]
VARIANTS["moc_kl"] = ("first MOC, CVAE KL weight 0.05 (the decoder uses its latent)", ["algo=moc_joint", *KL])
VARIANTS["official_kl"] = ("official MOC, CVAE KL weight 0.05", ["algo=moc_official", *KL])
VARIANTS["ppo_kl"] = ("PPO, CVAE KL weight 0.05", ["algo=ppo", *KL])
for _name in ("moc_kl", "official_kl", "ppo_kl"):
    VARIANTS[f"{_name}_fit20k"] = (VARIANTS[_name][0] + "; models fitted 20k steps", VARIANTS[_name][1] + FIT20K)
# rewards divided by the dataset's return-to-go std (model_env.reward_scale=auto): the critic can fit its targets
AUTO = ["model_env.reward_scale=auto"]
for _name in ("ppo_kl_fit20k", "official_kl_fit20k", "moc_kl_fit20k", "ppo_fit20k", "official_fit20k"):
    VARIANTS[f"{_name}_auto"] = (VARIANTS[_name][0] + "; rewards / return std", VARIANTS[_name][1] + AUTO)
# options that learn: the per-batch steps of beta and pi_O need a larger step size to move in 80 batches, and the
# deliberation cost xi (in units of the scaled rewards) makes switching cost something
BASE = ["algo=moc_official", *KL, *FIT20K, *AUTO]
VARIANTS["official_fast"] = ("official, KL 0.05, 20k fits, rewards / std, termination and pi_O lr 1e-3",
                             [*BASE, "algo.termination_lr=1e-3", "algo.option_lr=1e-3"])
VARIANTS["official_fast_xi"] = ("official, KL 0.05, 20k fits, rewards / std, termination and pi_O lr 1e-3, xi 0.01",
                                [*BASE, "algo.termination_lr=1e-3", "algo.option_lr=1e-3", "algo.xi=0.01"])
VARIANTS["official_xi"] = ("official, KL 0.05, 20k fits, rewards / std, xi 0.01", [*BASE, "algo.xi=0.01"])
VARIANTS["official_fast_xi_clip"] = ("official_fast_xi with PPO's Hopper clip 0.1 and gradient norm clipped at 0.5",
                                     [*BASE, "algo.termination_lr=1e-3", "algo.option_lr=1e-3", "algo.xi=0.01", "algo.clip_epsilon=0.1",
                                      "algo.max_grad_norm=0.5"])
FAST_XI = ["algo.termination_lr=1e-3", "algo.option_lr=1e-3", "algo.xi=0.01"]
VARIANTS["default_pess05"] = ("official_fast_xi with the pessimism threshold at 0.5 x the dataset's max discrepancy "
                              "(Hopper medium's table: 1.08)", [*BASE, *FAST_XI, "+model_env.pessimism.fraction=0.5"])
DEMO_BUDGET = ["train.total_frames=81920", "eval.every_frames=20480"]
VARIANTS["default_anneal"] = ("official_fast_xi with anneal_lr (every step size linearly to 0), over the demo's 82k frames",
                              [*BASE, *FAST_XI, "algo.anneal_lr=true", *DEMO_BUDGET])
VARIANTS["ppo_anneal"] = ("PPO, KL 0.05, 20k fits, rewards / std, anneal_lr, over 82k frames",
                          ["algo=ppo", *KL, *FIT20K, *AUTO, "algo.anneal_lr=true", *DEMO_BUDGET])
VARIANTS["default_1opt"] = ("the default MOC (with anneal_lr) with ONE option: MOC's machinery without options, next to PPO",
                            [*BASE, *FAST_XI, "algo.anneal_lr=true", "algo.num_options=1"])
VARIANTS["default_164k"] = ("the default MOC (official_fast_xi + anneal_lr) over 164k frames", [*BASE, *FAST_XI, "algo.anneal_lr=true"])
# a second development seed (evaluation seed 10007; not a results seed)
VARIANTS["default_164k_s10"] = ("default_164k on development seed 10", [*VARIANTS["default_164k"][1], "seed=10"])
VARIANTS["default_1opt_s10"] = ("default_1opt on development seed 10", [*VARIANTS["default_1opt"][1], "seed=10"])
VARIANTS["default_ev"] = ("the default MOC over 41k frames, to read its critic's explained variance",
                          [*BASE, *FAST_XI, "algo.anneal_lr=true", "train.total_frames=40960", "eval.every_frames=40960"])
# the model member drawn for every step instead of every episode (MBPO's rollouts): a policy cannot exploit one
# member's errors over a whole episode
DEFAULT = [*BASE, *FAST_XI, "algo.anneal_lr=true"]
VARIANTS["default_step"] = ("the default MOC, model member redrawn every step (member_mode step)", [*DEFAULT, "model_env.member_mode=step"])
VARIANTS["default_step_s10"] = ("default_step on development seed 10", [*VARIANTS["default_step"][1], "seed=10"])
# a smaller initial intra-option std: at e^0 = 1 (the CVAE prior's std) the exploring policy samples the whole
# behaviour distribution (the stochastic untrained agent scores about the data's 37) while evaluation acts on the
# latent mean (the decoder's mode, ~50-70): what training improves is not what evaluation measures
VARIANTS["default_std1"] = ("the default MOC, initial intra-option std e^-1", [*DEFAULT, "algo.init_log_std=-1.0"])
VARIANTS["default_std1_s10"] = ("default_std1 on development seed 10", [*VARIANTS["default_std1"][1], "seed=10"])
VARIANTS["default_step_std1"] = ("default_step with initial intra-option std e^-1", [*VARIANTS["default_step"][1], "algo.init_log_std=-1.0"])
VARIANTS["default_step_std1_s10"] = ("default_step_std1 on development seed 10", [*VARIANTS["default_step_std1"][1], "seed=10"])
for _seed in (0, 20, 30):  # the initial std e^-1 on the other development seeds
    VARIANTS[f"default_std1_s{_seed}" if _seed else "default_std1_s0"] = (f"default_std1 on development seed {_seed}",
                                                                        [*VARIANTS["default_std1"][1], f"seed={_seed}"])
for _seed in (20, 30):  # two more development seeds for the member_mode comparison
    VARIANTS[f"default_164k_s{_seed}"] = (f"default_164k on development seed {_seed}", [*VARIANTS["default_164k"][1], f"seed={_seed}"])
    VARIANTS[f"default_step_s{_seed}"] = (f"default_step on development seed {_seed}", [*VARIANTS["default_step"][1], f"seed={_seed}"])
# model episodes start at any dataset state instead of the data's start states: the agent trains on the whole
# gait the data covers, not only on what its own rollouts reach before the model (or the pessimism) ends them
for _seed in (0, 10, 20):
    _sfx = "" if _seed == 0 else f"_s{_seed}"
    VARIANTS[f"default_any{_sfx}"] = (f"the default MOC, model episodes start at any dataset state (reset_states any); seed {_seed}",
                                     [*DEFAULT, "model_env.reset_states=any", f"seed={_seed}"])
VARIANTS["hc_default"] = ("the default MOC on halfcheetah-medium (demo-size models fitted 20k steps)", [*DEFAULT, "env=halfcheetah"])
VARIANTS["hc_any"] = ("hc_default, model episodes start at any dataset state", [*DEFAULT, "env=halfcheetah", "model_env.reset_states=any"])
DIAG = ("termination_rate", "option_duration", "option_entropy", "option_usage_entropy", "termination_advantage_positive", "penalized_rate")


# the demo's settings when these experiments began (before issue 13 changed the defaults): every variant starts
# from them, so a row means the same thing whatever the current defaults are
LEGACY = {"cvae.kl_weight": "0.5", "model_env.reward_scale": "1.0", "ensemble.fit.max_steps": "3000", "cvae.fit.max_steps": "3000",
          "algo.minibatch_size": "256", "train.total_frames": "163840", "eval.every_frames": "40960"}


def overrides_of(name: str) -> list[str]:
    """LEGACY updated with the variant's overrides (hydra refuses a key given twice)."""
    merged = dict(LEGACY)
    for o in VARIANTS[name][1]:
        key, _, value = o.partition("=")
        merged[key] = value
    algo = merged.pop("algo", None)
    return ([f"algo={algo}"] if algo else []) + [f"{k}={v}" for k, v in merged.items()]


def run(names: list[str]) -> None:
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    for name in names:
        cfg = to_plain(compose("demo", [*overrides_of(name), f"run_dir={OUT / name}"]))
        s = train(cfg)
        print(f"{name}: final {s['final']['normalized_d4rl']:.1f}")


def table() -> str:
    from torchrl_offhrl.recipes.report import logged_tail_mean

    lines = [
        "| variant | what | final D4RL | best D4RL (frames) | untrained | model-real gap (final) | " + " | ".join(DIAG) + " |",
        "|" + "---|" * (6 + len(DIAG)),
    ]
    for name, (what, _) in VARIANTS.items():
        run = OUT / name
        if not (run / "summary.json").is_file():
            continue
        evals = json.loads((run / "evals.json").read_text())
        final, first = evals[-1], evals[0]
        best = max(evals[1:] or evals, key=lambda e: e["normalized_d4rl"])
        diag = [logged_tail_mean(run, k) for k in DIAG]
        gap = final.get("model_real_gap")
        lines.append(
            f"| {name} | {what} | {final['normalized_d4rl']:.1f} | {best['normalized_d4rl']:.1f} ({best['frames']}) | "
            f"{first['normalized_d4rl']:.1f} | {'n/a' if gap is None else f'{gap:.0f}'} | "
            + " | ".join("n/a" if v is None else f"{v:.3g}" for v in diag) + " |"
        )
    return "\n".join(lines)


# the same setting on several development seeds: mean +- std over the seeds that finished
GROUPS = {
    "default MOC (member_mode episode, reset_states initial)": ["default_164k", "default_164k_s10", "default_164k_s20", "default_164k_s30"],
    "member_mode step": ["default_step", "default_step_s10", "default_step_s20", "default_step_s30"],
    "reset_states any": ["default_any", "default_any_s10", "default_any_s20"],
    "initial std e^-1": ["default_std1_s0", "default_std1_s10", "default_std1_s20", "default_std1_s30"],
    "member_mode step, initial std e^-1": ["default_step_std1_s10"],
}


def seed_groups() -> str:
    import statistics

    def ms(xs):
        return f"{statistics.mean(xs):.1f} ± {statistics.stdev(xs):.1f}" if len(xs) > 1 else f"{xs[0]:.1f}"

    lines = ["| setting | development seeds | final D4RL | best D4RL | untrained | finals above their start |", "|---|---|---|---|---|---|"]
    for what, names in GROUPS.items():
        evs = [(n, json.loads((OUT / n / "evals.json").read_text())) for n in names if (OUT / n / "summary.json").is_file()]
        if not evs:
            continue
        seeds = [n.rsplit("_s", 1)[1] if n.rsplit("_s", 1)[-1].isdigit() else "0" for n, _ in evs]
        final = [e[-1]["normalized_d4rl"] for _, e in evs]
        best = [max(x["normalized_d4rl"] for x in e[1:]) for _, e in evs]
        start = [e[0]["normalized_d4rl"] for _, e in evs]
        lines.append(f"| {what} | {', '.join(seeds)} | {ms(final)} | {ms(best)} | {ms(start)} | "
                     f"{sum(f > s for f, s in zip(final, start))} / {len(evs)} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results moc-experiments", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("names", nargs="+", choices=sorted(VARIANTS))
    sub.add_parser("table")
    sub.add_parser("list")
    a = p.parse_args(argv)
    if a.cmd == "list":
        for name, (what, overrides) in VARIANTS.items():
            print(f"{name:28s} {what}  [{' '.join(overrides)}]")
        return 0
    if a.cmd == "run":
        run(a.names)
        return 0
    text = table()
    out = ROOT / "docs" / "results" / "moc_demo_experiments.md"
    groups = seed_groups()
    out.write_text("# MOC on the demo's setting (hopper-medium, 100k transitions, 164k frames, development seed 0)\n\n"
                   "Made by `offhrl results moc-experiments table`; 164k frames unless the row says otherwise; diagnostics are the mean "
                   "of the last 5 logged batches. Rows ending in `_s<N>` ran on development seed N (evaluation seed N * 1000 + 7); "
                   "`hc_*` rows on halfcheetah-medium.\n\n" + text + "\n\n"
                   "## The same settings over development seeds (hopper-medium, 164k frames)\n\n"
                   "One evaluation is 10 deterministic episodes that hardly differ, so a run's final score is one draw of which gait "
                   "the last policy settles in (a fall after ~300 steps near 30, a full episode near 90): single-seed rows say "
                   "little, these groups a bit more.\n\n" + groups + "\n")
    print(groups)
    print(text)
    return 0

