"""The paper's route to its block-stacking data: UOF trained online in the real env, shipped as small policies that collect datasets.

The paper's task-1 datasets come from UOF agents trained online for 20
("medium") and 50 ("medium-expert") epochs, task 2's from 200 epochs
(``../shared/reference/block_stacking.md``; an epoch is 50 cycles of 16
episodes x 25 steps: 20k frames). Here:

1. ``offhrl train algo=uof env=blockstack2 dataset=medium-expert train.online=true
   train.total_frames=400000 eval.every_frames=20000 train.snapshot_frames=[400000]``
   trains UOF in the real env in real actions (no models, no CVAE; the
   scripted dataset gives only the input statistics, see
   :mod:`~torchrl_offhrl.agents.uof`), evaluating per goal every epoch and
   keeping ``snapshot-<frames>.pt`` at the epochs asked for
   (``experiments/results/uof_online.py`` runs it and ships the snapshots);
2. :func:`ship_uof_policy` writes the acting part of a snapshot (the
   low-level actor and the first target Q-network of DIOL, which UOF picks
   options with: about 1 MB) with a card (env, epoch, the snapshot's real-env
   success per goal, the command) next to the locomotion policies;
3. :func:`load_uof_policy` gives back a :class:`UOFController`, which
   :func:`~torchrl_offhrl.data.stacking.collect_stacking` drives like the
   scripted controller (``offhrl collect blockstack2 --policy
   blockstack2-uof-epoch20``): greedy options (a new one when the running
   option's sub-goal is met), the actor's action for the option's sub-goal,
   and optionally the scripted levels' noise (``random_prob``, ``noise_std``).
"""
from __future__ import annotations

import json
import os
import shlex
import sys
from pathlib import Path

import torch
from tensordict import TensorDict

from ..agents import make_agent
from ..blockstack import goals as G
from ..data.collect import package_versions
from ..data.policies import POLICY_DIR
from ..registry import task_of
from ..utils import atomic_write, cache_dir, load_torch_file
from .pipeline import make_real_env

__all__ = ["EPOCH_FRAMES", "UOFController", "is_uof_policy", "load_uof_policy", "ship_uof_policy", "uof_dataset_path", "uof_route_dataset"]

_TARGET = "diol.target_value_network_params."
_ONLINE = "diol.value_network_params."
#: frames of one UOF epoch: 50 cycles x 16 episodes x 25 steps
EPOCH_FRAMES = 50 * 16 * 25


def _agent(env_id: str, algo: dict):
    env = make_real_env(env_id, None, num_envs=1)
    agent = make_agent("uof", env, algo, action_key="action", goal_key="sub_goal")
    env.close(raise_if_closed=False)  # never stepped: it may not have started
    return agent


def ship_uof_policy(run_dir, frames: int, name: str | None = None, dest=None, command: str | None = None) -> Path:
    """Write ``<name>.pt`` + ``<name>.json`` from ``run_dir/snapshot-<frames>.pt`` of an online UOF run; returns the ``.pt`` path.

    ``name`` defaults to ``<env>-uof-epoch<frames / 20000>``; ``dest`` to the
    shipped policies' folder (:data:`~torchrl_offhrl.data.policies.POLICY_DIR`).
    """
    run = Path(run_dir)
    snap = run / f"snapshot-{int(frames)}.pt"
    if not snap.is_file():
        kept = sorted(p.name for p in run.glob("snapshot-*.pt"))
        raise FileNotFoundError(f"{snap} does not exist (snapshots in {run}: {kept or 'none'}); train with train.snapshot_frames=[{frames}]")
    cfg = json.loads((run / "config.json").read_text())
    if cfg["algo"]["name"] != "uof" or not cfg.get("train", {}).get("online"):
        raise ValueError(f"{run} is not an online UOF run (algo={cfg['algo']['name']}, train.online={cfg.get('train', {}).get('online')})")
    env_id = cfg["env"]["env_id"]
    state = load_torch_file(snap, "UOF snapshot", f"train the run again with train.snapshot_frames=[{frames}]")
    agent = _agent(env_id, cfg["algo"])
    agent.load_state_dict(state["agent"])
    full = agent.policy.state_dict()
    keep = {k: v.clone() for k, v in full.items() if k.startswith("actor.")}
    keep.update({k: v[0].clone() for k, v in full.items() if k.startswith(_TARGET)})  # the network UOF picks options with
    epoch = int(frames) // EPOCH_FRAMES
    name = name or f"{cfg['env']['name']}-uof-epoch{epoch}"
    out = Path(dest) if dest is not None else POLICY_DIR
    out.mkdir(parents=True, exist_ok=True)
    pt = out / f"{name}.pt"
    rec = state.get("record") or {}
    card = {
        "name": name, "kind": "uof", "env_id": env_id, "n_blocks": task_of(env_id).n_blocks, "level": f"uof-epoch{epoch}",
        "algorithm": "UOF (DIOL high level + twin-critic DDPG with HER), trained online in the real env (torchrl_offhrl.agents.uof)",
        "algo": cfg["algo"], "frames": int(frames), "epochs": frames / EPOCH_FRAMES, "seed": cfg["seed"], "train_run": run.name,
        "eval": {k: rec.get(k) for k in ("success_per_goal", "success_per_goal_h50", "success_rate", "return_mean") if k in rec},
        "command": command or shlex.join(["offhrl", "train", *[f"{k}={v}" for k, v in (
            ("algo", "uof"), ("env", cfg["env"]["name"]), ("dataset", cfg["dataset"]), ("num_transitions", cfg.get("num_transitions")),
            ("dataset_seed", cfg.get("dataset_seed", 0)), ("train.online", "true"),
            ("train.total_frames", cfg["train"]["total_frames"]), ("eval.every_frames", cfg["eval"]["every_frames"]),
            ("train.snapshot_frames", f"[{int(frames)}]"), ("seed", cfg["seed"]))]]),
        "versions": package_versions(), "python": sys.version.split()[0],
    }
    with atomic_write(pt) as tmp:
        torch.save(keep, tmp)
    with atomic_write(pt.with_suffix(".json")) as tmp:
        Path(tmp).write_text(json.dumps(card, indent=1) + "\n")
    return pt


def _policy_file(name_or_path) -> Path:
    """The ``.pt`` file of a shipped name or of a given path."""
    text = os.fspath(name_or_path)
    return Path(text).expanduser().with_suffix(".pt") if ("/" in text or text.endswith((".pt", ".json"))) else POLICY_DIR / f"{text}.pt"


def uof_dataset_path(name: str, num_transitions: int, seed: int = 0, num_envs: int = 8, random_prob: float = 0.0, noise_std: float = 0.0) -> Path:
    """Where ``offhrl collect <env> --policy`` writes a dataset without ``--out``: the datasets cache, the noise in the name
    (greedy and noisy collections never share a file)."""
    noise = f"-rp{random_prob:g}-ns{noise_std:g}" if (random_prob or noise_std) else ""
    return cache_dir() / "datasets" / f"{name}-{num_transitions}-seed{seed}-envs{num_envs}{noise}.hdf5"


def is_uof_policy(name_or_path) -> bool:
    """Whether a shipped name or a ``.pt`` path is a UOF policy (its card says ``"kind": "uof"``)."""
    card = _policy_file(name_or_path).with_suffix(".json")
    return card.is_file() and json.loads(card.read_text()).get("kind") == "uof"


class UOFController:
    """A shipped UOF policy as a controller of :func:`~torchrl_offhrl.data.stacking.collect_stacking`.

    :meth:`select_option` keeps each env's option until its sub-goal is met
    (then, or at the start, the greedy option of DIOL's target network for the
    state and the goal); calling it maps ``(observation, option)`` to the
    actor's action for the option's sub-goal, with the scripted levels' noise
    when asked (``random_prob``: a uniform action, else Gaussian noise of
    ``noise_std`` on the three displacement entries).
    """

    def __init__(self, policy, n_blocks: int, card: dict, random_prob: float = 0.0, noise_std: float = 0.0, generator: torch.Generator | None = None):
        self.policy, self.n_blocks, self.card = policy, int(n_blocks), card
        self.random_prob, self.noise_std, self.generator = float(random_prob), float(noise_std), generator

    def select_option(self, obs: dict, option: torch.Tensor | None) -> torch.Tensor:
        td = TensorDict({"observation": obs["observation"].float(), "desired_goal": obs["desired_goal"].float()}, batch_size=obs["observation"].shape[:1])
        greedy = self.policy.option_values(td).argmax(-1)
        if option is None:
            return greedy
        return torch.where(G.option_met(option, obs["achieved_goal"]), greedy, option)

    @torch.no_grad()
    def __call__(self, observation: torch.Tensor, option: torch.Tensor) -> torch.Tensor:
        obs = observation.float()
        sub = G.sub_goals(obs, self.n_blocks)
        sub_goal = sub.gather(-2, option.long()[:, None, None].expand(-1, 1, sub.shape[-1])).squeeze(-2)
        action = self.policy.actor(TensorDict({"observation": obs, "sub_goal": sub_goal}, batch_size=obs.shape[:1])).get("action")
        if self.random_prob or self.noise_std:
            b = obs.shape[0]
            noise = torch.randn(b, 3, generator=self.generator) * self.noise_std
            action = action.clone()
            action[:, :3] = (action[:, :3] + noise).clamp(-1, 1)
            uniform = torch.rand(b, action.shape[-1], generator=self.generator) * 2 - 1
            action = torch.where((torch.rand(b, 1, generator=self.generator) < self.random_prob), uniform, action)
        return action


def load_uof_policy(name_or_path, random_prob: float = 0.0, noise_std: float = 0.0, generator: torch.Generator | None = None) -> UOFController:
    """The :class:`UOFController` of a shipped UOF policy (a name in the policies folder, or a ``.pt`` path with its card)."""
    pt = _policy_file(name_or_path)
    if not pt.is_file() or not pt.with_suffix(".json").is_file():
        raise FileNotFoundError(f"UOF policy {os.fspath(name_or_path)!r}: needs {pt} and {pt.with_suffix('.json')} (written by ship_uof_policy)")
    card = json.loads(pt.with_suffix(".json").read_text())
    if card.get("kind") != "uof":
        raise ValueError(f"{pt.with_suffix('.json')} is not a UOF policy card (kind={card.get('kind')!r})")
    agent = _agent(card["env_id"], card["algo"])
    saved = torch.load(pt, map_location="cpu", weights_only=True)
    full = agent.policy.state_dict()
    for k in full:
        if k.startswith("actor."):
            full[k] = saved[k]
        elif k.startswith((_TARGET, _ONLINE)):  # both target copies (and the unused online ones) from the shipped first target network
            full[k] = saved[_TARGET + k.split(".", 2)[2]].unsqueeze(0).expand_as(full[k]).clone()
    agent.policy.load_state_dict(full)
    agent.policy.eval()
    return UOFController(agent.policy, card["n_blocks"], card, random_prob, noise_std, generator)


def collect_with_uof_policy(env: str, policy, num_transitions: int, seed: int = 0, num_envs: int = 8, random_prob: float = 0.0,
                            noise_std: float = 0.0, progress: bool = True):
    """A block-stacking dataset collected by a shipped UOF policy (:func:`load_uof_policy`), and the cache path it belongs at.

    ``env`` is a block-stacking env name (``blockstack2``) the policy must act
    in; the dataset's name is ``<env>-<policy level>`` (``blockstack2-uof-epoch20``).
    Returns ``(dataset, path)``: :func:`uof_dataset_path` of that name and
    settings (the caller writes it there, or elsewhere).
    """
    from ..data.stacking import collect_stacking
    from ..registry import resolve_env, task_of

    env_id, _ = resolve_env(env)
    if not task_of(env_id).goal_conditioned:
        raise ValueError(f"a UOF policy collects block-stacking data (blockstack2 | blockstack3), not {env!r}")
    controller = load_uof_policy(policy, random_prob=random_prob, noise_std=noise_std, generator=torch.Generator().manual_seed(seed))
    if controller.card["env_id"] != env_id:
        raise ValueError(f"policy {os.fspath(policy)!r} acts in {controller.card['env_id']}, not {env_id}")
    name = f"{env}-{controller.card['name'].removeprefix(env + '-')}"
    ds = collect_stacking(env_id, num_transitions, num_envs=num_envs, seed=seed, controller=controller, progress=progress,
                          metadata={"dataset": name, "level": controller.card["level"], "random_prob": random_prob, "noise_std": noise_std})
    return ds, uof_dataset_path(name, num_transitions, seed, num_envs, random_prob, noise_std)


def uof_route_dataset(env: str, policy, num_transitions: int, seed: int = 0, num_envs: int = 8, random_prob: float = 0.0,
                      noise_std: float = 0.0) -> Path:
    """The cached file of :func:`collect_with_uof_policy` (collected and written there first when missing): the paper's data
    route as a path a run's ``dataset=`` takes."""
    from ..data import save_dataset

    card = _policy_file(policy).with_suffix(".json")
    shipped = json.loads(card.read_text())["name"] if card.is_file() else card.stem  # a missing card: load_uof_policy says what is needed
    path = uof_dataset_path(f"{env}-{shipped.removeprefix(env + '-')}", num_transitions, seed, num_envs, random_prob, noise_std)
    if not path.is_file():
        ds, path = collect_with_uof_policy(env, policy, num_transitions, seed, num_envs, random_prob, noise_std)
        save_dataset(ds, path)
    return path
