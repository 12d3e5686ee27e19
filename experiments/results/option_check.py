"""Are a MOC run's options alive, temporally extended and learned (not as initialised)? Issue 13's option criteria.

    offhrl results option-check outputs/results/demo/moc-hopper-medium-seed4 [...]   # prints a markdown table
    offhrl results option-check --out docs/results/demo/option_check.md outputs/results/demo/moc-*

Per run, on 20,000 states of the run's own dataset:

* ``beta`` of each option: mean and spread over states (std, 5-95% range) of
  the trained agent, next to a freshly initialised agent of the same seed
  and config (what the run started from, up to the RNG draws of the model
  fits), and the mean absolute change per state;
* the entropy of pi_O(.|s), trained and fresh;
* from the training logs (mean of the last 5 logged batches): termination
  rate, mean option duration, pi_O entropy on the states the agent visited;
* from the final evaluation: each option's share of the steps and whether
  every option is active in some evaluation episode.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def check(run: Path, n_states: int = 20_000) -> dict:
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.recipes.config import resolve_dataset
    from torchrl_offhrl.recipes.evaluation import load_run_agent
    from torchrl_offhrl.recipes.report import logged_tail_mean

    cfg, env, agent, state, cvae = load_run_agent(run)
    if cfg["algo"]["name"] != "moc":
        raise SystemExit(f"{run}: a {cfg['algo']['name']} run, not a MOC one")
    torch.manual_seed(int(cfg["seed"]))
    fresh = make_agent("moc", env, cfg["algo"], action_key="latent_action" if cvae is not None else "action")  # as load_run_agent
    data = resolve_dataset(cfg)
    g = torch.Generator().manual_seed(0)
    obs = data.data["observation"][torch.randint(len(data), (n_states,), generator=g)].float()
    out = {"run": run.name}
    with torch.no_grad():
        heads = {}
        for name, a in (("trained", agent), ("fresh", fresh)):
            logits, _, _, beta = a.policy.heads(obs)
            heads[name] = (beta, torch.distributions.Categorical(logits=logits).entropy())
    (bt, ht), (bf, hf) = heads["trained"], heads["fresh"]
    for o in range(bt.shape[-1]):
        q = torch.quantile(bt[:, o], torch.tensor([0.05, 0.95]))
        out[f"beta{o}"] = f"{bt[:, o].mean():.3f} ± {bt[:, o].std():.3f} [{q[0]:.3f}, {q[1]:.3f}]"
        out[f"beta{o}_fresh"] = f"{bf[:, o].mean():.3f} ± {bf[:, o].std():.3f}"
        out[f"beta{o}_change"] = f"{(bt[:, o] - bf[:, o]).abs().mean():.3f}"
    out["pi_O_entropy"] = f"{ht.mean():.3f} (fresh {hf.mean():.3f})"
    for k in ("termination_rate", "option_duration", "option_entropy"):
        v = logged_tail_mean(run, k)
        out[k] = "n/a" if v is None else f"{v:.3g}"
    final = json.loads((run / "evals.json").read_text())[-1]
    out["final_usage"] = " / ".join(f"{u:.2f}" for u in final.get("option_usage_mean", []))
    usage_file = run / "option_usage.pt"
    if usage_file.is_file():
        usage = torch.load(usage_file, weights_only=True)
        out["every_option_active"] = "yes" if bool((usage.amax(0) > 0).all()) else "no"
    env.close()
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results option-check", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=None, help="also write the table to this markdown file")
    a = p.parse_args(argv)
    rows = [check(r) for r in a.runs]
    cols = list(rows[0])
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in rows]
    text = "\n".join(lines)
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text("# MOC option check\n\nMade by `offhrl results option-check --out " + str(a.out) + " " + " ".join(map(str, a.runs))
                         + "` (see the script's docstring for what each column is).\n\n" + text + "\n")
    return 0

