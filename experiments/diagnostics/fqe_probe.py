"""Does fitted Q evaluation rank a run's intermediate policies as the real env does?

    python experiments/diagnostics/fqe_probe.py RUN_DIR [RUN_DIR ...] [--steps 5000] [--out FILE.json]

For every ``snapshot-<frames>.pt`` of a run (the runs of
``experiments/results/robustness.py`` keep one per evaluation after step 0), the policy's
deterministic action is computed at every dataset state (through the run's
CVAE decoder, as the latent transform decodes it), and all of them are scored
by one batched FQE fit (:func:`torchrl_offhrl.objectives.fqe.fitted_q_evaluation`)
on the run's own dataset: value at the data's start states, and at every
dataset state. The real-env score is the run's own record at that
evaluation (read, never used to compute a value). Prints, per run, the real
score of the policy each signal picks and whether it is within 5 of the best.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_offhrl.envs import LatentActionTransform
from torchrl_offhrl.objectives.fqe import fitted_q_evaluation
from torchrl_offhrl.recipes.config import auto_reward_scale, resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.utils import load_torch_file


@torch.no_grad()
def policy_actions(agent, cvae, bound: float, obs: torch.Tensor, chunk: int = 20000) -> torch.Tensor:
    """The agent's deterministic real action at each state (an option policy picks its option afresh at each), decoded
    as the run's envs decode it (:class:`~torchrl_offhrl.envs.LatentActionTransform`: clipped to the box, then the decoder)."""
    decode = LatentActionTransform(cvae.decoder, latent_bound=bound) if cvae is not None else None
    out = []
    for o in obs.split(chunk):
        td = TensorDict({"observation": o, "is_init": torch.ones(o.shape[0], 1, dtype=torch.bool)}, batch_size=[o.shape[0]])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            agent.eval_policy(td)
        out.append(decode.inv(td)["action"] if decode is not None else td[agent.action_key])
    return torch.cat(out)


def probe(run_dir: Path, steps: int, seed: int = 0, gamma: float = 0.99, tau: float = 0.005) -> dict:
    cfg, _, agent, state, cvae = load_run_agent(run_dir, num_envs=1)
    data = resolve_dataset(cfg)
    records = {int(r["frames"]): r for r in state["records"]} if "records" in state else {
        int(r["frames"]): r for r in json.loads((run_dir / "evals.json").read_text())}
    bound = cfg.get("model_env", {}).get("latent_bound", 2.0)
    td = data.data
    obs, act = td["observation"], td["action"]
    nobs, rew, term = td["next", "observation"], td["next", "reward"].reshape(-1), td["next", "terminated"].reshape(-1)
    starts = data.initial_observations()
    snaps = sorted(run_dir.glob("snapshot-*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[-1]))
    frames, next_actions, start_actions = [], [], []
    for p in snaps:
        agent.load_state_dict(load_torch_file(p, "snapshot", "")["agent"])
        frames.append(int(re.findall(r"\d+", p.name)[-1]))
        next_actions.append(policy_actions(agent, cvae, bound, nobs))
        start_actions.append(policy_actions(agent, cvae, bound, starts))
    stats = data.stats()
    scale = auto_reward_scale(data, gamma)
    fit = fitted_q_evaluation(obs, act, rew, nobs, term, torch.stack(next_actions), starts, torch.stack(start_actions), steps=steps, gamma=gamma, tau=tau,
                              reward_scale=scale, obs_loc=stats.obs_mean, obs_scale=stats.obs_std, seed=seed)
    real = [records[f]["normalized_d4rl"] for f in frames]
    return {"run": str(run_dir), "frames": frames, "real": real, "fqe_start": fit["value"].tolist(), "td_error": fit["td_error"].tolist()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--gamma", type=float, default=0.99, help="the discount of the value FQE estimates")
    p.add_argument("--tau", type=float, default=0.005, help="the target critics' Polyak rate")
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    results, hits = [], 0
    for run in a.runs:
        r = probe(run, a.steps, gamma=a.gamma, tau=a.tau)
        results.append(r)
        k = max(range(len(r["frames"])), key=lambda i: r["fqe_start"][i])
        best = max(r["real"])
        hits += best - r["real"][k] <= 5
        print(f"{run}: FQE picks {r['frames'][k]} (real {r['real'][k]:.1f}; best {best:.1f}; last {r['real'][-1]:.1f})")
        for f, x, v, e in zip(r["frames"], r["real"], r["fqe_start"], r["td_error"]):
            print(f"   {f:6d} real {x:5.1f}  fqe {v:8.2f}  td {e:.4f}")
    print(f"FQE within 5 of best: {hits}/{len(results)}")
    if a.out:
        a.out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
