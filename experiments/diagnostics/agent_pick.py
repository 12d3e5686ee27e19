"""Can an offline signal choose between two agents' final policies trained on the same dataset?

    python experiments/diagnostics/agent_pick.py [VARIANT ...] [--seeds tuning|evaluation|all]   # default: shipped std037, tuning

Reads the archived robustness runs (``docs/results/demo_robustness_runs/<variant>/d<seed>[a<agent>]``, the
records of ``offhrl results robustness run``). For every dataset seed with two or more agent seeds, each
agent's *final* evaluation record gives its model-env signals (the P-MDP rollouts every evaluation makes:
``model_return_mean``, ``model_discounted_mean``, the worst member's ``model_return_min_member`` and
``model_discounted_min_member``, and the share of penalised model episodes, lower picked), and the policy
the signal ranks first is "returned". Ties go to the lowest agent seed: never to the real score, which is
read only to score the pick. Printed per signal: in how many dataset seeds the picked policy beats both its
own untrained start and the data (the demo's bar), beside picking the lowest agent seed, the best agent
(``any``: one of them beats both) and all agents beating both.

The question it answers: with seeds batched (several agents for the price of little more than one), would a
pick among their final policies raise the demo's success rate above one agent's?
"""
from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "docs" / "results" / "demo_robustness_runs"
SIGNALS = ("model_return_mean", "model_discounted_mean", "model_return_min_member", "model_discounted_min_member",
           "lowest_model_return_mean", "lowest_model_return_min_member", "fewest_penalised", "lowest_agent_seed")


def runs(variant: str) -> dict[int, dict[int, tuple[list, dict]]]:
    """``{dataset seed: {agent seed: (evaluation records, demo summary)}}`` of a variant's archived runs."""
    out: dict[int, dict] = defaultdict(dict)
    for d in sorted((ROOT / variant).glob("d*")):
        m = re.fullmatch(r"d(\d+)(?:a(\d+))?", d.name)
        if m and (d / "demo_summary.json").is_file():
            out[int(m[1])][int(m[2] or 0)] = (json.loads((d / "evals.json").read_text()), json.loads((d / "demo_summary.json").read_text()))
    return out


def value(signal: str, final: dict, agent: int) -> float:
    if signal == "fewest_penalised":
        return -final["model_penalized"]
    if signal == "lowest_agent_seed":
        return -agent
    if signal.startswith("lowest_"):
        return -final[signal[len("lowest_"):]]
    return final[signal]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="*", default=["shipped", "std037"])
    ap.add_argument("--seeds", choices=["tuning", "evaluation", "all"], default="tuning",
                    help="dataset seeds 1-3 (where choices are made), 4 and up (reporting only), or both")
    a = ap.parse_args(argv)
    keep = {"tuning": lambda d: d <= 3, "evaluation": lambda d: d >= 4, "all": lambda d: True}[a.seeds]
    totals: dict[str, list[int]] = {s: [0, 0] for s in (*SIGNALS, "any agent", "every agent")}
    for v in a.variants:
        by = {d: ag for d, ag in runs(v).items() if len(ag) >= 2 and keep(d)}
        if not by:
            print(f"{v}: no dataset seed with two agent seeds")
            continue
        print(f"## {v}: {len(by)} dataset seeds with 2+ agents")
        for s in SIGNALS:
            ok = anyok = allok = 0
            picks = []
            for d, agents in sorted(by.items()):
                rows = []
                for agent, (evals, summary) in sorted(agents.items()):
                    f = evals[-1]
                    real, start, data = f["normalized_d4rl"], evals[0]["normalized_d4rl"], summary["behaviour_normalized_d4rl"]
                    rows.append((value(s, f, agent), -agent, real, real > start and real > data))
                pick = max(rows, key=lambda r: (r[0], r[1]))  # ties: the lowest agent seed
                ok += pick[3]
                anyok += any(r[3] for r in rows)
                allok += all(r[3] for r in rows)
                picks.append(f"d{d}: {pick[2]:.1f} ({' / '.join(f'{r[2]:.1f}' for r in rows)})")
                totals[s][0] += pick[3]
                totals[s][1] += 1
                if s == SIGNALS[0]:
                    for k, hit in (("any agent", any(r[3] for r in rows)), ("every agent", all(r[3] for r in rows))):
                        totals[k][0] += hit
                        totals[k][1] += 1
            print(f"{s:31s} picked beats both {ok}/{len(by)}; any {anyok}, all {allok}   {'; '.join(picks)}")
    if len(a.variants) > 1:
        print(f"## all {len(a.variants)} variants together ({a.seeds} dataset seeds): picked policy beats its start and the data")
        for k, (hit, n) in totals.items():
            print(f"{k:31s} {hit}/{n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
