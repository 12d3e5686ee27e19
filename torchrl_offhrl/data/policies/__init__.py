"""Shipped behaviour policies for D4RL-style dataset generation.

D4RL's protocol draws its "medium" and "expert" datasets from SAC policies:
"expert" is the fully trained policy, "medium" a checkpoint of the same run
stopped at about a third of the expert's return. This folder holds such
policies as pairs of files:

* ``<name>.pt``: the state dict of the actor built by
  :func:`torchrl_offhrl.data.policies.actors.make_behaviour_actor`;
* ``<name>.json``: its card (env id, level, training and evaluation facts,
  the command that reproduces it, package versions, actor dimensions).

Names are ``<env>-<level>``, e.g. ``hopper-medium`` or ``halfcheetah-expert``.
A policy is made from a run of ``scripts/train_behaviour.py`` with
:func:`ship_policy` (or ``python -m torchrl_offhrl.data.policies ship ...``)
and read back with :func:`load_policy`.
"""
from __future__ import annotations

import json
import os
import shlex
from pathlib import Path
from typing import Any

import torch

from ...registry import resolve_env
from ...rollouts import evaluate_policy
from ...scores import normalized_score
from ...utils import atomic_write, one_thread
from ..collect import make_gym_env, package_versions
from .actors import ALGORITHMS, make_behaviour_actor, pick_checkpoint

__all__ = ["POLICY_DIR", "PolicyNotFoundError", "list_policies", "load_policy", "ship_policy"]

#: The folder of the shipped policies (``<name>.pt`` + ``<name>.json``).
POLICY_DIR = Path(__file__).resolve().parent

#: Default seed of the evaluation done by :func:`ship_policy`. Training-time
#: evaluations use ``10_000 + steps``; this one stays clear of them for runs
#: shorter than about 1.2M steps, so the shipped numbers come from fresh episodes.
SHIP_EVAL_SEED = 1_234_567

_LEVELS = ("medium", "expert")
_CARD_KEYS = ("env_id", "obs_dim", "act_dim", "action_low", "action_high", "hidden")


class PolicyNotFoundError(LookupError):
    """No shipped policy has this name (the message lists the shipped ones and how to make one)."""


def list_policies(folder: str | os.PathLike | None = None, kind: str = "behaviour") -> list[str]:
    """Names of the shipped policies of a ``kind``, sorted (those with both a ``.pt`` and a ``.json``).

    ``kind`` is the card's ``"kind"``: ``"behaviour"`` (the default, and
    cards without one: the locomotion actors :func:`load_policy` builds),
    ``"uof"`` (block-stacking UOF policies,
    :func:`torchrl_offhrl.recipes.uof_policies.load_uof_policy`) or ``"all"``.

    Examples:
        >>> from torchrl_offhrl.data.policies import list_policies
        >>> isinstance(list_policies(), list)
        True
    """
    root = Path(folder) if folder is not None else POLICY_DIR
    names = []
    for p in sorted(root.glob("*.pt")):
        card = p.with_suffix(".json")
        if card.is_file() and kind in ("all", json.loads(card.read_text()).get("kind", "behaviour")):
            names.append(p.stem)
    return names


def load_policy(name_or_path: str | os.PathLike) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Load a behaviour policy and its card.

    Args:
        name_or_path: a shipped name (see :func:`list_policies`), e.g.
            ``"hopper-medium"``, or the path of a ``.pt`` file whose card is
            the ``.json`` file next to it.

    Returns:
        ``(actor, card)``: the tanh-Gaussian actor of
        :func:`~torchrl_offhrl.data.policies.actors.make_behaviour_actor` in eval
        mode (it samples under ``ExplorationType.RANDOM`` and returns its mean
        under ``DETERMINISTIC``), and the card as a dict.

    Raises:
        PolicyNotFoundError: an unknown name; the message lists the shipped
            policies and the commands that make one.
        FileNotFoundError: a path without its ``.pt`` or ``.json`` file.
        ValueError: a card that lacks what is needed to build the actor.
    """
    pt = _resolve(name_or_path)
    card_path = pt.with_suffix(".json")
    if not pt.is_file() or not card_path.is_file():
        missing = [str(p) for p in (pt, card_path) if not p.is_file()]
        raise FileNotFoundError(
            f"behaviour policy {str(name_or_path)!r}: missing {missing}. A policy is a pair "
            f"<name>.pt (actor state dict) + <name>.json (its card), written by "
            f"torchrl_offhrl.data.policies.ship_policy."
        )
    card = json.loads(card_path.read_text())
    if card.get("kind", "behaviour") != "behaviour":
        raise ValueError(f"{card_path} is a {card['kind']!r} policy, not a behaviour actor: load it with "
                         "torchrl_offhrl.recipes.uof_policies.load_uof_policy (or collect with `offhrl collect <env> --policy NAME`)")
    lacking = [k for k in _CARD_KEYS if k not in card]
    if lacking:
        raise ValueError(f"{card_path}: the card lacks {lacking}; cannot build the actor.")
    actor = _build_actor(card)
    state = torch.load(pt, map_location="cpu", weights_only=True)
    actor.load_state_dict(state)
    actor.eval()
    card.setdefault("name", pt.stem)
    card["path"] = str(pt)
    return actor, card


def card_returns(actor, env, seed: int, max_steps: int = 1000, deterministic: bool = False) -> torch.Tensor:
    """The returns of a policy card's evaluation: one episode per env of ``env``, seeded as :func:`ship_policy` does.

    Calling it with the card's ``eval`` settings (``episodes`` envs,
    ``seed``, ``max_steps``) reproduces the card's figures for its weights.
    """
    with one_thread():  # evaluate_policy seeds a stochastic evaluation's samples with `seed` itself (forked)
        return evaluate_policy(env, actor, env.batch_size[0], max_steps=max_steps, deterministic=deterministic, seed=seed)


def ship_policy(
    run_dir: str | os.PathLike,
    name: str,
    level: str,
    steps: int | None = None,
    target: float | None = None,
    episodes: int = 10,
    seed: int = SHIP_EVAL_SEED,
    command: str | None = None,
    dest: str | os.PathLike | None = None,
    progress: bool = False,
    max_steps: int = 1000,
    note: str | None = None,
) -> Path:
    """Pick a checkpoint of a behaviour run, re-evaluate it and write it as ``<name>.pt`` + ``<name>.json``.

    Args:
        run_dir: the ``--out`` folder of ``scripts/train_behaviour.py``
            (:func:`~torchrl_offhrl.recipes.behaviour.train_behaviour`):
            ``actor_<steps>.pt`` files and ``evals.json``.
        name: the policy name, ``<env>-<level>`` by convention
            (``"hopper-medium"``).
        level: ``"medium"`` or ``"expert"``.
        steps: ship the checkpoint of exactly this many environment steps.
        target: otherwise, the checkpoint whose training-time stochastic
            return is closest to ``target``; ``None`` (and no ``steps``) picks
            the best one (D4RL's "expert"). For "medium" use about a third of
            the best return.
        episodes: fresh episodes of the re-evaluation (at least 10), run in
            parallel in ``make_gym_env(env_id, num_envs=episodes)``, both
            sampling (stochastic) and with the mean action (deterministic).
        seed: seed of the re-evaluation (envs and action sampling).
        command: the command line that reproduces the policy, stored in the
            card; by default one is composed from the run (training command
            and the ship command with the exact checkpoint).
        dest: folder written to; defaults to the shipped policies folder.
        progress: print what is chosen and the evaluation result.
        max_steps: step limit of each evaluation episode (1000, the limit
            of the MuJoCo envs; smaller only for quick tests).
        note: free text stored in the card as ``note`` (e.g. how the run
            was resumed, or why this checkpoint).

    The card also records ``train_wall_s``: the run's wall time from its
    start to this checkpoint, evaluations included, summed over resumed
    sessions (time lost after the last saved state of an interrupted
    session is not counted; sessions may have used different devices or
    thread counts).

    Returns:
        The path of the ``.pt`` file. Both files are written atomically
        (temporary name, then rename; the ``.json`` last).
    """

    if level not in _LEVELS:
        raise ValueError(f"ship_policy: level must be one of {_LEVELS}, got {level!r}.")
    if episodes < 10:
        raise ValueError(f"ship_policy: evaluate over at least 10 episodes (got {episodes}).")
    if not name or any(c in name for c in "/\\ ") or name.endswith((".pt", ".json")):
        raise ValueError(f"ship_policy: {name!r} is not a valid policy name (e.g. 'hopper-medium').")
    run = Path(run_dir).expanduser()
    evals_path = run / "evals.json"
    if not evals_path.is_file():
        raise FileNotFoundError(
            f"{run}: no evals.json. Pass the --out folder of scripts/train_behaviour.py "
            f"(it holds actor_<steps>.pt files and evals.json)."
        )
    info = json.loads(evals_path.read_text())
    records = info.get("evals", [])
    if not records:
        raise ValueError(f"{evals_path}: no evaluation records; let the run reach its first evaluation.")
    if steps is not None:
        matches = [r for r in records if r["steps"] == steps]
        if not matches:
            raise ValueError(
                f"{evals_path}: no checkpoint at {steps} steps; evaluated steps are "
                f"{[r['steps'] for r in records]}."
            )
        record, how = matches[0], f"steps={steps}"
    else:
        record = pick_checkpoint(records, target)
        how = "best stochastic return" if target is None else f"stochastic return closest to {target:g}"
    ckpt = run / f"actor_{record['steps']}.pt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: checkpoint listed in evals.json but not on disk.")
    env_id = info["env_id"]
    hidden = list(info.get("hidden", (256, 256)))
    algorithm = info.get("algorithm", "sac")  # runs from before CrossQ was added are SAC runs
    if algorithm not in ALGORITHMS:
        raise ValueError(f"{evals_path}: unknown algorithm {algorithm!r}; known: {sorted(ALGORITHMS)}.")

    env = make_gym_env(env_id, num_envs=episodes)
    try:
        obs_dim = int(env.observation_spec["observation"].shape[-1])
        spec = env.action_spec
        act_dim = int(spec.shape[-1])
        low = spec.space.low.reshape(-1, act_dim)[0].float()
        high = spec.space.high.reshape(-1, act_dim)[0].float()
        card: dict[str, Any] = {
            "name": name,
            "env_id": env_id,
            "level": level,
            "algorithm": ALGORITHMS[algorithm]["loss"],
            "hidden": hidden,
            "obs_dim": obs_dim,
            "act_dim": act_dim,
            "action_low": low.tolist(),
            "action_high": high.tolist(),
        }
        actor = _build_actor(card)
        actor.load_state_dict(torch.load(ckpt, map_location="cpu", weights_only=True))
        actor.eval()
        evaluation: dict[str, Any] = {"episodes": episodes, "seed": seed, "max_steps": max_steps}
        for det in (False, True):
            rets = card_returns(actor, env, seed, max_steps, deterministic=det)
            evaluation["deterministic" if det else "stochastic"] = {
                "mean": float(rets.mean()),
                "std": float(rets.std()),
            }
    finally:
        env.close()
    evaluation["normalized_d4rl"] = normalized_score(env_id, evaluation["stochastic"]["mean"])
    evaluation["training_eval"] = {k: record[k] for k in ("stochastic", "deterministic") if k in record}
    if command is None:
        eval_every = records[0]["steps"]
        algo_flag = "" if algorithm == "sac" else f" --algorithm {algorithm}"
        critic_hidden = info.get("critic_hidden", hidden)
        if critic_hidden != hidden:
            algo_flag += " --critic-hidden " + " ".join(str(w) for w in critic_hidden)
        train = (
            f"python scripts/train_behaviour.py {env_id}{algo_flag} --steps {max(r['steps'] for r in records)} "
            f"--eval-every {eval_every} --seed {info.get('seed', 0)} --out {shlex.quote(str(run))}"
        )
        ship = (
            f"python -m torchrl_offhrl.data.policies ship {shlex.quote(str(run))} {name} "
            f"--level {level} --steps {record['steps']} --episodes {episodes} --seed {seed}"
        )
        if max_steps != 1000:
            ship += f" --max-steps {max_steps}"
        command = f"{train} && {ship}"
        if hidden != [256, 256]:
            command += f"  # the run used hidden={hidden}: train_behaviour(..., hidden={tuple(hidden)})"
    card.update(
        {
            "train_steps": int(record["steps"]),
            "train_wall_s": record.get("wall_s"),
            "seed": info.get("seed"),
            "selection": how,
            "eval": evaluation,
            "command": command,
            "versions": package_versions(),
            "source": {"run_dir": str(run), "checkpoint": ckpt.name},
        }
    )
    if note:
        card["note"] = note
    out = Path(dest).expanduser() if dest is not None else POLICY_DIR
    pt = out / f"{name}.pt"
    # the card is renamed into place last: list_policies only lists complete pairs
    with atomic_write(pt.with_suffix(".json")) as tmp_card, atomic_write(pt) as tmp_pt:
        torch.save(actor.state_dict(), tmp_pt)
        Path(tmp_card).write_text(json.dumps(card, indent=1) + "\n")
    if progress:
        st, de = evaluation["stochastic"], evaluation["deterministic"]
        print(
            f"shipped {name} ({env_id}, {level}) from {ckpt} ({how}): stochastic "
            f"{st['mean']:.1f} ± {st['std']:.1f}, deterministic {de['mean']:.1f} ± {de['std']:.1f} "
            f"over {episodes} episodes -> {pt}"
        )
    return pt


# ------------------------------------------------------------------ helpers
def _build_actor(card: dict) -> torch.nn.Module:
    return make_behaviour_actor(
        int(card["obs_dim"]),
        int(card["act_dim"]),
        torch.as_tensor(card["action_low"], dtype=torch.float32),
        torch.as_tensor(card["action_high"], dtype=torch.float32),
        tuple(card["hidden"]),
    )


def _resolve(name_or_path: str | os.PathLike) -> Path:
    """The ``.pt`` path of a shipped name or of a given path."""
    text = os.fspath(name_or_path)
    looks_like_path = (
        isinstance(name_or_path, os.PathLike)
        or text.endswith((".pt", ".json"))
        or os.sep in text
        or "/" in text
    )
    if looks_like_path:
        return Path(text).expanduser().with_suffix(".pt")
    if text in list_policies(kind="all"):  # a UOF policy's name too: load_policy then says what to load it with
        return POLICY_DIR / f"{text}.pt"
    raise PolicyNotFoundError(missing_policy_message(text))


#: Env steps of SAC that reach every level (the expert's >= 85 D4RL
#: normalised included), from the runs behind the shipped policies: Hopper's
#: expert came at 200k steps, HalfCheetah's at 1.26M.
_RUN_STEPS = {"hopper": 300_000, "halfcheetah": 1_500_000}


def missing_policy_message(name: str) -> str:
    """The error text for a policy name that is not shipped: what exists and how to make it."""
    available = list_policies()
    short, _, level = name.partition("-")
    try:
        env_id, short = resolve_env(short)
    except ValueError:
        env_id = "<EnvId-v5>"
    level = level if level in _LEVELS else "medium"
    out = f"outputs/behaviour/{short}"
    pick = "--fraction 0.33" if level == "medium" else ""  # expert: the best checkpoint
    return (
        f"no shipped behaviour policy named {name!r}. Shipped policies: "
        f"{available if available else 'none yet'} (in {POLICY_DIR}). To make it, train a SAC "
        f"run and ship a checkpoint of it:\n"
        f"    python scripts/train_behaviour.py {env_id} --steps {_RUN_STEPS.get(short, 300_000)} --out {out}\n"
        f"    python -m torchrl_offhrl.data.policies ship {out} {short}-{level} --level {level} {pick}".rstrip()
        + "\nor pass a policy yourself (policy=<path to a .pt with its .json card, or an actor>)."
    )
