"""Move a generated dataset to another machine as its actions alone, and rebuild it there bit for bit.

    python scripts/action_pack.py pack hopper-medium .packs/hopper-medium.pt      # a named (cached) dataset, or an .hdf5 file
    python scripts/action_pack.py unpack .packs/hopper-medium.pt [--workers 8]    # -> the dataset cache, under its usual name

``unpack`` replays the actions in MuJoCo (one process per env stream) and
refuses the result unless it has the packed content hash; it then writes the
dataset where :func:`~torchrl_offhrl.data.named_dataset` looks for it
(``$TORCHRL_OFFHRL_CACHE/datasets/``), so ``offhrl train dataset=medium``
and ``offhrl results table1 run`` find it and a run there resumes anywhere on
the original data. What it is for: ``scripts/gpu_runs.sh``, on a lent GPU
machine whose minutes would not cover generating the dataset.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack", help="write a dataset's actions, metadata and content hash")
    a.add_argument("dataset", help="a named dataset (hopper-medium; generated and cached if absent) or an .hdf5 file")
    a.add_argument("out", type=Path)
    b = sub.add_parser("unpack", help="rebuild a packed dataset into the dataset cache")
    b.add_argument("pack", type=Path)
    b.add_argument("--workers", type=int, default=None, help="replay processes (default: one per CPU, at most one per env stream)")
    args = p.parse_args(argv)

    from torchrl_offhrl.data import load_dataset, named_dataset, save_dataset
    from torchrl_offhrl.data.action_pack import load_action_pack, read_action_pack, save_action_pack
    from torchrl_offhrl.data.catalog import dataset_path
    from torchrl_offhrl.utils import atomic_write

    if args.cmd == "pack":
        path = Path(args.dataset)
        ds = load_dataset(path) if path.suffix in (".hdf5", ".h5") else named_dataset(args.dataset)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        save_action_pack(ds, args.out)
        print(f"{args.out}: {len(ds):,} transitions of {ds.metadata.get('dataset', ds.metadata['env_id'])}, content hash {ds.content_hash()} "
              f"({args.out.stat().st_size / 2**20:.1f} MiB)")
        return 0
    pack = read_action_pack(args.pack)
    meta, packed = pack["metadata"], pack["content_hash"]
    target = dataset_path(meta["dataset"], len(pack["actions"]), int(meta["seed"]), int(meta["num_envs"]))
    if target.is_file() and load_dataset(target).content_hash() == packed:  # checked before the replay, which costs far more
        print(f"{target}: already there, the same data ({packed})")
        return 0
    ds = load_action_pack(args.pack, workers=args.workers)
    with atomic_write(target) as tmp:  # whole or absent: a killed unpack never leaves a file that would be loaded
        save_dataset(ds, tmp, compression=None)  # ~15% larger than gzip's, and written in seconds instead of a minute
    print(f"{target}: rebuilt from {args.pack}, content hash {ds.content_hash()} (as packed)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
