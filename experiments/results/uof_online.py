"""The paper's route to its block-stacking data: UOF trained online in the real env, its 20- and 50-epoch policies shipped.

    offhrl results uof-online run [--env blockstack2] [--epochs 20 50] [--seed 0]    # resumable; outputs/uof_online/
    offhrl results uof-online ship [--env blockstack2] [--epochs 20 50]              # torchrl_offhrl/data/policies/<env>-uof-epoch<N>
    offhrl results uof-online collect [--env blockstack2] [--epochs 20 50] [-n 100000]  # a dataset per shipped policy
    offhrl results uof-online report [--env blockstack2]                             # docs/results/uof_online/ + figure

``run`` is ``offhrl train algo=uof env=<env> dataset=medium-expert train.online=true``
with UOF's schedule: epochs of 50 cycles x 16 episodes x 25 steps (20k
frames; 40 + 40 updates per cycle: ``configs/algo/uof.yaml``), a real-env
evaluation per epoch (30 episodes per goal, success within 25 and 50 steps),
and a snapshot at each epoch of ``--epochs`` (the paper: task 1 20 and 50,
task 2 200). The scripted medium-expert data (100k transitions per level)
gives only the input statistics. Rerunning resumes from the checkpoint, and
a larger ``--epochs`` continues the same run.

``ship`` writes each snapshot as a policy with its card
(:func:`torchrl_offhrl.recipes.uof_policies.ship_uof_policy`); then
``offhrl collect blockstack2 --policy blockstack2-uof-epoch20 --out data.hdf5``
collects a dataset with it and ``offhrl train ... dataset=data.hdf5`` trains on it.

``report`` archives the run (config, evaluations, summary) to
``docs/results/uof_online/`` and writes the per-epoch success table and curve.
Seed 0: this run makes data, it is not an evaluation of UOF.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
from torchrl_offhrl.recipes.uof_policies import EPOCH_FRAMES as EPOCH  # noqa: E402  (frames of one UOF epoch)


def run_dir(env: str, seed: int) -> Path:
    return ROOT / "outputs" / "uof_online" / f"uof-{env}-online-seed{seed}"


def overrides(env: str, epochs: list[int], seed: int) -> list[str]:
    frames = sorted(e * EPOCH for e in epochs)
    return ["algo=uof", f"env={env}", "dataset=medium-expert", "num_transitions=100000", "train.online=true", f"train.total_frames={frames[-1]}",
            f"eval.every_frames={EPOCH}", f"train.snapshot_frames=[{','.join(map(str, frames))}]", f"seed={seed}", f"run_dir={run_dir(env, seed)}"]


def run(env: str, epochs: list[int], seed: int) -> None:
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    train(to_plain(compose("offline_train", overrides(env, epochs, seed))))


def ship(env: str, epochs: list[int], seed: int) -> None:
    from torchrl_offhrl.recipes.uof_policies import ship_uof_policy

    cfg = json.loads((run_dir(env, seed) / "config.json").read_text())  # the run's own epochs, whatever is shipped now
    ran = sorted({*(int(f) // EPOCH for f in cfg["train"]["snapshot_frames"]), int(cfg["train"]["total_frames"]) // EPOCH})
    cmd = "offhrl results uof-online run " + shlex.join(["--env", env, "--epochs", *map(str, ran), "--seed", str(seed)])
    for e in epochs:
        pt = ship_uof_policy(run_dir(env, seed), e * EPOCH, command=cmd)
        card = json.loads(pt.with_suffix(".json").read_text())
        print(f"{pt} ({pt.stat().st_size / 1e6:.2f} MB): success per goal {card['eval'].get('success_per_goal')}")


def collect(env: str, epochs: list[int], transitions: int) -> None:
    """Collect ``transitions`` with each shipped policy (greedy, as `offhrl collect --policy`); their per-goal success goes to
    ``docs/results/uof_online/datasets.json`` (the datasets stay in the cache: `offhrl train dataset=<file>` trains on them)."""
    import subprocess

    record = ROOT / "docs" / "results" / "uof_online" / "datasets.json"
    done = json.loads(record.read_text()) if record.is_file() else {}
    from torchrl_offhrl.data import load_dataset
    from torchrl_offhrl.recipes.uof_policies import uof_dataset_path

    for e in epochs:
        name = f"{env}-uof-epoch{e}"
        out = uof_dataset_path(name, transitions)  # where `offhrl collect --policy` writes it by default
        # the command a user types, in its own process (this module sits below the command line)
        if subprocess.run([sys.executable, "-m", "torchrl_offhrl.cli", "collect", env, "--policy", name, "-n", str(transitions)]).returncode != 0:
            raise SystemExit(f"collecting with {name} failed")
        meta = load_dataset(out).metadata
        done[name] = {"transitions": transitions, "goal_success": meta["goal_success"], "goal_episodes": meta["goal_episodes"],
                      "return_mean": meta["returns"]["mean"], "command": f"offhrl collect {env} --policy {name} -n {transitions}"}
    record.parent.mkdir(parents=True, exist_ok=True)
    record.write_text(json.dumps(done, indent=1) + "\n")


def report(env: str, seed: int) -> str:
    from torchrl_offhrl.recipes.report import archive_run, load_run, plot_goal_success

    out = ROOT / "docs" / "results" / "uof_online"
    src = run_dir(env, seed)
    kept = out / src.name
    if (src / "summary.json").is_file():
        archive_run(src, kept)
    elif (src / "evals.json").is_file():  # still running: what it has so far
        kept.mkdir(parents=True, exist_ok=True)
        for name in ("config.json", "evals.json"):
            (kept / name).write_bytes((src / name).read_bytes())
    r = load_run(kept)
    evals = r["evals"]
    plot_goal_success([evals], out / f"success_{env}.png", label="UOF online", title=f"UOF trained online in {r['config']['env']['env_id']}",
                      xlabel="real-env frames")
    lines = [f"# UOF trained online in the real env ({env})", "",
             "The paper's route to its block-stacking data: UOF trained online, its 20- and 50-epoch policies collect the task-1 datasets "
             "(task 2: 200 epochs). Made by `offhrl results uof-online report` from the run of `offhrl results uof-online run` "
             f"(seed {seed}; one epoch = 50 cycles x 16 episodes x 25 steps = {EPOCH} frames; 30 evaluation episodes per goal, "
             "deterministic, success within 25 and 50 steps).", "",
             f"![success per goal](success_{env}.png)", "",
             "| epoch | frames | success per goal, horizon 25 | horizon 50 | minutes since the process (re)started |", "|---|---|---|---|---|"]
    for e in evals:
        lines.append(f"| {e['step'] / EPOCH:g} | {e['step']} | {' '.join(f'{x:.2f}' for x in e['success_per_goal'])} | "
                     f"{' '.join(f'{x:.2f}' for x in e['success_per_goal_h50'])} | {e.get('wall_s', 0) / 60:.0f} |")
    record = out / "datasets.json"
    data = {k: v for k, v in (json.loads(record.read_text()) if record.is_file() else {}).items() if k.startswith(f"{env}-")}
    if data:
        lines += ["", "Datasets collected with the shipped policies (`offhrl results uof-online collect`: greedy options and actions, "
                  "no added noise; the share of episodes of each goal that reached it within 25 steps):", "",
                  "| policy | transitions | success per goal | return | command |", "|---|---|---|---|---|"]
        for k, v in sorted(data.items()):
            rates = " / ".join("n/a" if x is None else f"{x:.2f}" for x in v["goal_success"].values())
            lines.append(f"| {k} | {v['transitions']} | {rates} | {v['return_mean']:.1f} | `{v['command']}` |")
    if r["summary"] is None:
        lines += ["", f"The run had not finished when this page was made ({evals[-1]['step']} frames of {r['config']['train']['total_frames']})."]
    text = "\n".join(lines) + "\n"
    (out / "README.md").write_text(text)
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results uof-online", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cmd", choices=["run", "ship", "collect", "report"])
    p.add_argument("-n", "--transitions", type=int, default=100_000, help="collect: transitions per policy")
    p.add_argument("--env", default="blockstack2", choices=["blockstack2", "blockstack3"])
    p.add_argument("--epochs", nargs="+", type=int, default=[20, 50], help="epochs to keep (and ship); the run lasts the largest")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.cmd == "run":
        run(a.env, a.epochs, a.seed)
    elif a.cmd == "ship":
        ship(a.env, a.epochs, a.seed)
    elif a.cmd == "collect":
        collect(a.env, a.epochs, a.transitions)
    else:
        print(report(a.env, a.seed))
    return 0

