"""``offhrl``: the command line of torchrl_offhrl.

Hyper-parameters live in the hydra configs under ``configs/`` (``offline_train.yaml``
and its ``algo/`` and ``env/`` groups); commands that train or fit take
hydra-style ``key=value`` overrides after their own options.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time

EPILOG = """examples:
  offhrl demo                                         # the embedded demo (short budget, 13-30 min on 2 CPUs with its fits)
  offhrl policies                                     # shipped behaviour policies and their returns
  offhrl collect hopper medium -n 1000000             # D4RL-protocol dataset, cached
  offhrl fit env=hopper dataset=medium                # ensemble + CVAE, cached
  offhrl train algo=moc env=hopper dataset=medium     # on the model env: algo=moc|ppo|sac|morel
  offhrl train algo=iql env=hopper dataset=medium     # on the dataset itself: algo=iql|cql|td3bc|bc
  offhrl evaluate outputs/runs/moc-hopper-medium-seed0 --episodes 10
  offhrl aggregate outputs/runs/moc-hopper-medium-seed* --out outputs/report
  offhrl report outputs/runs/*-seed* --out docs/results/table1   # the paper's Table I
  offhrl tune models env=hopper dataset=medium        # the paper's model search on Ray Tune (pip install 'torchrl-offhrl[tune]')
  offhrl sweep --algos moc ppo --seeds 4 5 6 env=hopper   # runs as Ray Tune trials, one per core; --address joins a cluster
"""


def cmd_policies(args) -> int:
    from .data import list_policies, load_policy
    from .data.policies import POLICY_DIR

    names = list_policies()
    if not names:
        print("no behaviour policies are shipped; train one with scripts/train_behaviour.py")
    if names:
        print(f"{'name':22s} {'env':16s} {'steps':>8s} {'return (stoch.)':>18s} {'D4RL score':>10s}")
    for n in names:
        _, card = load_policy(n)
        ev = card["eval"]
        st = ev["stochastic"]
        print(f"{n:22s} {card['env_id']:16s} {card['train_steps']:8d} {st['mean']:10.1f} ± {st['std']:5.1f} {ev.get('normalized_d4rl') or float('nan'):10.1f}")
    uof = list_policies(kind="uof")
    if uof:
        print(f"\n{'UOF policy':22s} {'env':16s} {'frames':>8s}  real-env success per goal (horizon 25)")
        for n in uof:
            card = json.loads((POLICY_DIR / f"{n}.json").read_text())
            rates = " ".join(f"{x:.2f}" for x in card.get("eval", {}).get("success_per_goal") or [])
            print(f"{n:22s} {card['env_id']:16s} {card['frames']:8d}  {rates}")
    return 0


def cmd_collect(args) -> int:
    from .data import export_minari, named_dataset, save_dataset
    from .data.catalog import dataset_path

    t0 = time.time()
    if args.policy:  # the paper's route: a UOF policy trained online collects the block-stacking data
        from .recipes.uof_policies import collect_with_uof_policy

        if args.level not in (None, "uof"):
            raise ValueError(f"--policy collects block-stacking data with a shipped UOF policy: `offhrl collect blockstack2 --policy "
                             f"blockstack2-uof-epoch20`; got env {args.env!r}, level {args.level!r}")
        ds, default_out = collect_with_uof_policy(args.env, args.policy, args.num_transitions, args.seed, args.num_envs,
                                                  args.random_prob, args.noise_std)
        args.out = args.out or str(default_out)
    else:
        if args.level is None:
            raise ValueError("give a level (random | medium | expert | medium-expert), or --policy for block stacking")
        name = f"{args.env}-{args.level}"
        ds = named_dataset(name, num_transitions=args.num_transitions, seed=args.seed, num_envs=args.num_envs)
    print(ds)
    r = ds.metadata.get("returns", {})
    if not r.get("complete", True):
        eps = f"{r.get('episodes')} episodes (none finished within the budget)"
    else:
        eps = f"{r.get('episodes')} complete episodes" + (f" (+{r['unfinished']} cut short by the budget, left out)" if r.get("unfinished") else "")
    where = "" if args.policy else f"cached at {dataset_path(name, args.num_transitions, args.seed, args.num_envs)} "
    print(f"{len(ds)} transitions, {eps}, return {r.get('mean', float('nan')):.1f} ± {r.get('std', float('nan')):.1f}; "
          f"{where}({time.time() - t0:.0f} s)")
    if "goal_success" in ds.metadata:  # the block-stacking datasets
        rates = ", ".join(f"goal {k}: {v:.2f}" for k, v in ds.metadata["goal_success"].items() if v is not None)
        print(f"episodes that reached their goal (horizon {ds.metadata.get('horizon')}): {rates}")
    if args.out:
        save_dataset(ds, args.out)
        print(f"written to {args.out}")
    if args.minari_id:
        export_minari(ds, args.minari_id)
        print(f"exported as the local Minari dataset {args.minari_id}")
    return 0


def cmd_fit(args) -> int:
    from .recipes.config import compose, model_config, resolve_dataset
    from .recipes.pipeline import fit_or_load_models
    from .recipes.schema import validate_config
    from .utils import to_plain

    cfg = compose("offline_train", args.overrides, "fit")
    validate_config(to_plain(cfg))
    data = resolve_dataset(cfg)
    _, _, info = fit_or_load_models(model_config(cfg), data)
    for name in ("ensemble", "cvae"):
        hist = info.get(f"{name}_history")
        val = hist[-1].get("val_loss") if hist else None
        print(f"{name}: {info[name]}" + (f", validation loss per member {[round(v, 4) for v in val]}" if val else ""))
    print(f"models in {info['model_dir']}")
    return 0


def cmd_train(args) -> int:
    from .recipes.config import compose
    from .recipes.summary import format_summary
    from .recipes.train import train

    cfg = compose("offline_train", args.overrides, "train")
    if args.seeds:  # one run per seed, their updates batched (the dataset agents)
        from .recipes.seed_runs import train_seeds

        for summary in train_seeds(cfg, args.seeds):
            print("\n" + format_summary(summary))
        return 0
    print("\n" + format_summary(train(cfg)))
    return 0


def cmd_evaluate(args) -> int:
    from .recipes.evaluation import evaluate_run

    res = evaluate_run(args.run_dir, episodes=args.episodes, seed=args.seed, frames_dir=args.frames, deterministic=not args.stochastic,
                       policy=args.policy)
    print(json.dumps(res, indent=2))
    return 0


def _command_line() -> str:
    """This command as typed (``offhrl ...``), for the page it writes to name the command that rebuilds it."""
    import shlex

    return "offhrl " + shlex.join(sys.argv[1:])


def cmd_aggregate(args) -> int:
    from pathlib import Path

    from .recipes.report import aggregate

    print(aggregate(args.runs, args.out, made_by=_command_line()))
    written = [f for f in ("results.md", "results.csv", "transfer.csv", "curves.png") if (Path(args.out) / f).is_file()]
    print(f"\nwritten: {args.out}/" + ", ".join(written))
    return 0


def cmd_report(args) -> int:
    from .recipes.report import paper_table

    print(paper_table(args.runs, args.out, min_seeds=args.min_seeds, made_by=_command_line()))
    print(f"\nwritten: {args.out}/table.md, table.csv, curves_<env>-<dataset>.png (and variants.md for columns that are not a shipped algorithm's)")
    return 0


def _ray_options(s) -> None:
    s.add_argument("--name", help="experiment name (its folder; the same name resumes an interrupted one)")
    s.add_argument("--out", default="outputs", help="results go to OUT/tune/<name>/ or OUT/sweeps/<name>/")
    s.add_argument("--address", help="join this Ray cluster (default: $RAY_ADDRESS, else a local Ray on this machine)")
    s.add_argument("--num-cpus", type=int, help="CPUs of the local Ray (default: this machine's cores)")
    s.add_argument("--cpus-per-trial", type=int, default=1, help="CPUs (and torch threads) per trial: trials never oversubscribe")
    s.add_argument("--gpus-per-trial", type=float, default=0.0)
    s.add_argument("--max-concurrent", type=int, help="at most this many trials at once (default: as many as the CPUs allow)")


def _ray_kwargs(args) -> dict:
    return {"out_root": args.out, "address": args.address, "num_cpus": args.num_cpus, "cpus_per_trial": args.cpus_per_trial,
            "gpus_per_trial": args.gpus_per_trial, "max_concurrent": args.max_concurrent}


def cmd_tune(args) -> int:
    from .recipes.tune import tune_search

    best = tune_search(args.preset, args.overrides, name=args.name, num_samples=args.num_samples, **_ray_kwargs(args))
    print(best["table"])
    print(f"written: {best['out']}/results.md, results.csv, best.json ({best['wall_s']:.0f} s)")
    print("best: " + json.dumps(best["settings"]))
    print(f"reuse it: {best['command']}")
    return 0


def cmd_sweep(args) -> int:
    from .recipes.tune import sweep

    res = sweep(args.algos, args.envs, args.datasets, args.seeds, args.overrides, name=args.name or "sweep", **_ray_kwargs(args))
    print(res["table"])
    print(f"written: {res['out']}/results.md, results.csv; the runs: {res['out']}/<algo>-<env>-<dataset>-seed<k>/ "
          f"(offhrl aggregate / offhrl report read them)")
    return 0


def checkout_root() -> "Path":
    """The repository checkout whose ``experiments/`` makes the results pages: the checkout this package is installed from
    in editable mode (``make install``), else the current directory, else ``$TORCHRL_OFFHRL_ROOT`` (which also says where
    the pages are written: ``experiments.results.paths``)."""
    from pathlib import Path

    candidates = [Path(__file__).resolve().parents[1], Path.cwd().resolve()]
    if os.environ.get("TORCHRL_OFFHRL_ROOT"):
        candidates.append(Path(os.environ["TORCHRL_OFFHRL_ROOT"]).resolve())
    return next((c for c in candidates if (c / "experiments" / "results" / "__init__.py").is_file()), candidates[-1])


def cmd_results(args) -> int:
    """``offhrl results``: the experiments that make the results pages are not part of the installed library; they live in
    the repository's ``experiments/results/`` (``python -m experiments.results ...`` from a checkout), and this forwards to it."""
    root = checkout_root()
    if not (root / "experiments" / "results" / "__init__.py").is_file():
        raise SystemExit(f"offhrl results: the results pages are made by the experiments of a checkout of torchrl_offhrl "
                         f"(experiments/results/, not installed with the library), and {root} has none: run it from the "
                         "repository root, install the checkout with `pip install -e .`, or set TORCHRL_OFFHRL_ROOT")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from experiments.results import main as results_main

    return results_main(args.args)


def cmd_demo(args) -> int:
    from .recipes.demo import run_demo

    run_demo(args.overrides)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="offhrl",
        description="Offline hierarchical RL with TorchRL: datasets, pessimistic models, MOC / PPO / SAC on the model env, "
                    "IQL / CQL / TD3+BC / BC baselines on the data.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="command")

    s = sub.add_parser("demo", help="the embedded demo: medium data -> models -> MOC -> real-env evaluation (13-30 min on 2 CPUs, models fitted to convergence)",
                       description="Collects a small Hopper-v5 dataset with the shipped medium policy, fits the ensemble and the CVAE, "
                       "trains MOC on the pessimistic model for a short budget, evaluates in the real env and prints a summary. "
                       "Extra key=value arguments override configs/demo.yaml.")
    s.add_argument("overrides", nargs="*", help="hydra overrides of configs/demo.yaml, e.g. train.total_frames=50000")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("policies", help="list the shipped behaviour policies with their evaluation returns")
    s.set_defaults(func=cmd_policies)

    s = sub.add_parser("collect", help="generate (or load from the cache) a D4RL-protocol dataset",
                       description="Rolls out a shipped behaviour policy (stochastic, as D4RL) or uniform actions in the real env. "
                       "Cached under $TORCHRL_OFFHRL_CACHE (default ~/.cache/torchrl_offhrl)/datasets; asking again loads the file.")
    s.add_argument("env", help="hopper | halfcheetah | blockstack2 | blockstack3 (block stacking: a scripted controller with noise)")
    s.add_argument("level", nargs="?", help="random | medium | expert | medium-expert (block stacking: medium | expert | medium-expert); "
                                            "leave out with --policy")
    s.add_argument("-n", "--num-transitions", type=int, default=1_000_000, help="transitions (per part for medium-expert); default 1M as D4RL")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--num-envs", type=int, default=8, help="envs stepped side by side")
    s.add_argument("--out", help="also write the dataset to this HDF5 file")
    s.add_argument("--minari-id", help="also export it as a local Minari dataset with this id (needs `pip install minari`)")
    s.add_argument("--policy", help="block stacking: collect with this shipped UOF policy (e.g. blockstack2-uof-epoch20, or a .pt path; "
                                    "`offhrl policies` lists them) instead of the scripted controller; written to --out (default: the "
                                    "datasets cache), train on it with dataset=<that file>")
    s.add_argument("--random-prob", type=float, default=0.0, help="with --policy: share of uniform actions (default 0: the greedy policy)")
    s.add_argument("--noise-std", type=float, default=0.0, help="with --policy: Gaussian noise on the displacement (default 0)")
    s.set_defaults(func=cmd_collect)

    s = sub.add_parser("fit", help="fit (or load from the cache) the dynamics ensemble and the CVAE on a dataset",
                       description="Uses configs/offline_train.yaml; e.g. `offhrl fit env=hopper dataset=medium ensemble.fit.max_steps=null`.")
    s.add_argument("overrides", nargs="*", help="hydra overrides of configs/offline_train.yaml")
    s.set_defaults(func=cmd_fit)

    s = sub.add_parser("train", help="train an agent offline (configs/offline_train.yaml): on the model env (algo=moc|ppo|sac|morel) "
                                     "or on the dataset itself (algo=iql|cql|td3bc|bc)",
                       description="Same as examples/offline_train.py: e.g. `offhrl train algo=moc env=hopper dataset=medium seed=1`. "
                       "Rerunning the same command resumes from the run's checkpoint.")
    s.add_argument("overrides", nargs="*", help="hydra overrides of configs/offline_train.yaml")
    s.add_argument("--seeds", nargs="+", type=int, help="train one run per seed with their updates batched as one computation "
                   "(the agents that learn from the dataset: bc, td3bc, iql, cql; ppo, moc, sac and mopo on the model env: one env of N x E envs, "
                   "sac and mopo each seed with its own replay buffer), "
                   "e.g. --seeds 4 5 6 7 8")
    s.set_defaults(func=cmd_train)

    s = sub.add_parser("evaluate", help="evaluate a run's checkpoint in the real env (normalised score, optional frames)")
    s.add_argument("run_dir", help="a run directory written by `offhrl train`")
    s.add_argument("--episodes", type=int, default=10)
    s.add_argument("--seed", type=int, default=12345)
    s.add_argument("--stochastic", action="store_true", help="sample actions and options instead of the deterministic policy")
    s.add_argument("--frames", help="save PNG frames of the first episode here (headless: set MUJOCO_GL=egl or osmesa)")
    s.add_argument("--policy", choices=("selected", "last"), default="selected",
                   help="selected (default): the policy the run returned by offline policy selection (selected.pt; runs without one: "
                        "the last); last: the checkpoint's")
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("aggregate", help="aggregate several runs (seeds) into one table and one figure")
    s.add_argument("runs", nargs="+", help="run directories, or folders of them (e.g. an `offhrl sweep` folder)")
    s.add_argument("--out", default="outputs/report")
    s.set_defaults(func=cmd_aggregate)

    s = sub.add_parser("report", help="the paper's Table I from run directories: env x dataset rows, one column per algorithm "
                                      "(MOC, PPO, SAC, MOReL, MOPO, IQL, CQL, TD3+BC, BC), the behaviour data, published scores apart")
    s.add_argument("runs", nargs="+", help="run directories (every algorithm and seed), or folders of them (e.g. an `offhrl sweep` folder)")
    s.add_argument("--out", default="outputs/report")
    s.add_argument("--min-seeds", type=int, default=3, help="cells with fewer seeds are listed under 'Missing cells' (default 3)")
    s.set_defaults(func=cmd_report)

    s = sub.add_parser("tune", help="a hyper-parameter search on Ray Tune: the paper's presets (models, pessimism, moc) or your YAML",
                       description="e.g. `offhrl tune models env=hopper dataset=medium` (configs/tune/models.yaml: 10 random combinations "
                       "of the paper's grid, each model chosen by its validation loss). Needs `pip install 'torchrl-offhrl[tune]'`.")
    s.add_argument("preset", help="configs/tune/<preset>.yaml, or a path to a search YAML")
    s.add_argument("overrides", nargs="*", help="hydra overrides of configs/offline_train.yaml for every trial")
    s.add_argument("--num-samples", type=int, help="how many grid points to draw (default: the preset's num_samples; all of them if it has none)")
    _ray_options(s)
    s.set_defaults(func=cmd_tune)

    s = sub.add_parser("sweep", help="algorithms x envs x datasets x seeds as Ray Tune trials (ordinary run directories; finished ones skipped)",
                       description="e.g. `offhrl sweep --algos moc ppo --envs hopper --seeds 4 5 6 train.total_frames=204800`. Rerunning "
                       "the same command resumes an interrupted sweep. Needs `pip install 'torchrl-offhrl[tune]'`.")
    s.add_argument("--algos", nargs="+", required=True)
    s.add_argument("--envs", nargs="+", default=["hopper"])
    s.add_argument("--datasets", nargs="+", default=["medium"])
    s.add_argument("--seeds", nargs="+", type=int, default=[4, 5, 6])
    s.add_argument("overrides", nargs="*", help="hydra overrides of configs/offline_train.yaml for every run")
    _ray_options(s)
    s.set_defaults(func=cmd_sweep)

    s = sub.add_parser("results", help="every results page under docs/results/: run a preset's experiments and rebuild its pages "
                                       "(offhrl results list)", add_help=False,
                       description="offhrl results list | rebuild [PRESET ...] | PRESET ARGS... (e.g. `offhrl results table1 report "
                                   "--scale demo`); a checkout of the repository is where the pages and runs live.")
    s.add_argument("args", nargs=argparse.REMAINDER, help="list, rebuild [PRESET ...], or a preset and its own arguments")
    s.set_defaults(func=cmd_results)
    return p


def overrides_last(argv: list[str]) -> list[str]:
    """``argv`` with its hydra ``key=value`` overrides moved to just after the command's own positional arguments.

    So overrides may come anywhere after the command: without it an option
    taking several values swallows the overrides that follow it
    (``--seeds 4 5 6 train.total_frames=204800``) and overrides after an
    option are refused. An argv with ``--`` is left as given.

    Examples:
        >>> overrides_last(["sweep", "--seeds", "4", "5", "train.total_frames=8", "--name", "x"])
        ['sweep', 'train.total_frames=8', '--seeds', '4', '5', '--name', 'x']
        >>> overrides_last(["tune", "moc", "--name", "x", "env=hopper"])
        ['tune', 'moc', 'env=hopper', '--name', 'x']
    """
    if "--" in argv:
        return list(argv)
    is_override = [("=" in a and not a.startswith("-")) for a in argv]
    overrides = [a for a, o in zip(argv, is_override) if o]
    rest = [a for a, o in zip(argv, is_override) if not o]
    first_option = next((i for i, a in enumerate(rest) if i > 0 and a.startswith("-")), len(rest))
    return rest[:first_option] + overrides + rest[first_option:]


def main(argv: list[str] | None = None) -> int:
    """Run a command; a user error (missing file or policy, bad name or value) prints one message and returns 2."""
    from .data import DatasetError, PolicyNotFoundError

    argv = sys.argv[1:] if argv is None else list(argv)
    # a results preset parses its own arguments (its --extra takes key=value overrides where it says)
    args = build_parser().parse_args(argv if argv[:1] == ["results"] else overrides_last(argv))
    # TorchRL's INFO lines (spec inference, spec checks) are noise on a command line; torchrl sets
    # its logger's level when imported (RL_LOGGING_LEVEL), so import it first, unless the user chose
    import torchrl  # noqa: F401

    if "RL_LOGGING_LEVEL" not in os.environ:
        logging.getLogger("torchrl").setLevel(logging.WARNING)
    from .recipes.rundir import RunInUseError
    from .utils import DiskWriteError
    from .recipes.tune import SearchInterrupted

    try:
        return args.func(args)
    except (DatasetError, PolicyNotFoundError, FileNotFoundError, ValueError, ImportError, ConnectionError, RunInUseError, DiskWriteError) as err:
        print(f"offhrl {args.command}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a folder that cannot take a file, met outside atomic_write (a run folder, a lock): one line too
        from .utils import DISK_ERRNOS, disk_write_error

        if err.errno not in DISK_ERRNOS:
            raise
        print(f"offhrl {args.command}: error: {disk_write_error(err, folder=err.filename)}", file=sys.stderr)
        return 2
    except SearchInterrupted as err:  # Ctrl-C during a search or sweep: the tables stay as they were
        print(f"offhrl {args.command}: {err}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
