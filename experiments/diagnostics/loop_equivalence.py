"""Does a change to the training loop keep its behaviour? Thirteen tiny runs, one per setting, recorded for comparison.

    python experiments/diagnostics/loop_equivalence.py record NAME [CASE ...]    # -> /tmp/loop_equivalence/NAME.json
    python experiments/diagnostics/loop_equivalence.py compare BEFORE AFTER

Each case is a tiny config of one setting of ``offhrl train`` (MOC, MOC with
model-LCB selection, PPO without the CVAE, SAC, IQL, TD3+BC, CQL, MOPO, MOC transfer, PPO from
scratch, PPO online, UOF and BC on block stacking) on small generated
datasets; ``record`` keeps every evaluation record and the summary (times and
paths left out), ``compare`` says per case whether they are identical. Run
``record`` on the code before and after a change, on the same machine.
"""
import json, os, sys, shutil
from pathlib import Path
ROOT_OUT = Path(os.environ.get("LOOP_EQUIVALENCE_DIR", "/tmp/loop_equivalence"))
os.environ["TORCHRL_OFFHRL_CACHE"] = str(ROOT_OUT / "cache")
import torch
torch.set_num_threads(1)
from torchrl_offhrl.data import collect_dataset, save_dataset
from torchrl_offhrl.data.stacking import generate_stacking_dataset
from torchrl_offhrl.recipes.config import compose
from torchrl_offhrl.recipes.train import train
from torchrl_offhrl.utils import to_plain

D = ROOT_OUT / "data"
hop, bs = D / "hopper.hdf5", D / "bs2.hdf5"
TINY = ["ensemble.hidden_sizes=[32,32]", "ensemble.fit.max_steps=40", "cvae.hidden_sizes=[32,32]", "cvae.fit.max_steps=40",
        "collector.num_envs=4", "train.total_frames=256", "eval.every_frames=128", "eval.episodes=2", "eval.max_steps=40",
        "train.total_updates=200", "eval.every_updates=100"]
TRANSFER = ["transfer.task=backward", "transfer.online_frames=256", "transfer.num_envs=2", "transfer.eval_every_frames=128"]
BS = ["eval.episodes=2", "ensemble.hidden_sizes=[16]", "ensemble.num_models=2", "ensemble.fit.max_steps=30", "cvae.hidden_sizes=[16]",
      "cvae.fit.max_steps=30", "algo.hidden_sizes=[16]"]
CASES = {
    "moc": ["algo=moc", "algo.frames_per_batch=64", "algo.epochs=2", *TINY],
    "moc_lcb": ["algo=moc", "algo.frames_per_batch=64", "algo.epochs=2", "selection.criterion=model_lcb", "selection.include_start=true", *TINY],
    "ppo_nocvae": ["algo=ppo", "algo.frames_per_batch=64", "algo.epochs=2", "ablation.no_cvae=true", *TINY],
    "sac": ["algo=sac", "algo.init_random_frames=64", "algo.utd_ratio=0.25", "algo.batch_size=32", *TINY],
    "iql": ["algo=iql", "algo.batch_size=32", *TINY],
    "td3bc": ["algo=td3bc", "algo.batch_size=32", *TINY],
    "cql": ["algo=cql", "algo.batch_size=32", "algo.policy_eval_start=100", *TINY],
    "mopo": ["algo=mopo", "algo.rollout_batch_size=8", "algo.rollout_freq=16", "algo.batch_size=32", "ensemble.num_models=3",
             "ensemble.num_elites=2", *TINY],
    "moc_transfer": ["algo=moc", "algo.frames_per_batch=64", "algo.epochs=2", *TINY, *TRANSFER],
    "ppo_scratch": ["algo=ppo", "algo.frames_per_batch=64", "algo.epochs=2", *TINY, *TRANSFER, "transfer.from_scratch=true"],
    "ppo_online": ["algo=ppo", "algo.frames_per_batch=64", "algo.epochs=2", "train.online=true", *TINY],
    "uof_bs": ["algo=uof", "env=blockstack2", *BS, "algo.batch_size=16", "train.total_frames=800", "eval.every_frames=400", "algo.buffer_size=5000"],
    "bc_bs": ["algo=bc", "env=blockstack2", *BS, "algo.batch_size=16", "train.total_updates=200", "eval.every_updates=100"],
}


def strip(x):
    if isinstance(x, dict):
        return {k: strip(v) for k, v in x.items() if k not in ("wall_s", "plots", "run_dir")}
    if isinstance(x, list):
        return [strip(v) for v in x]
    return x


if sys.argv[1:2] == ["compare"]:
    b, a = (json.loads((ROOT_OUT / f"{n}.json").read_text()) for n in sys.argv[2:4])
    for k in b:
        same = k in a and strip(b[k]) == strip(a[k])
        print(f"{k}: {'identical' if same else 'DIFFERENT'}")
    sys.exit(0)
D.mkdir(parents=True, exist_ok=True)
if not hop.exists():
    save_dataset(collect_dataset("Hopper-v5", 1200, num_envs=4, seed=0, progress=False), hop)
if not bs.exists():
    save_dataset(generate_stacking_dataset("BlockStack2-v0", "medium", 800, seed=0, progress=False), bs)
out = {}
which = sys.argv[3:] or list(CASES)
for name in which:
    ds = bs if name.endswith("_bs") else hop
    run_dir = ROOT_OUT / "runs" / sys.argv[2] / name
    shutil.rmtree(run_dir, ignore_errors=True)
    s = train(to_plain(compose("offline_train", [f"dataset={ds}", f"run_dir={run_dir}", *CASES[name]])), progress=False)
    evals = json.loads((run_dir / "evals.json").read_text())
    drop = {"wall_s"}
    out[name] = {"evals": [{k: v for k, v in e.items() if k not in drop} for e in evals],
                 "summary": {k: v for k, v in s.items() if k not in ("timing", "run_dir", "frames_per_s", "updates_per_s", "update_time_s", "data_s", "models_s", "total_s", "wall_s")},
                 "files": sorted(p.name for p in run_dir.iterdir())}
    print(name, "ok", flush=True)
(ROOT_OUT / f"{sys.argv[2]}.json").write_text(json.dumps(out, indent=1, sort_keys=True, default=str))
