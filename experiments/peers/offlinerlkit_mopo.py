"""OfflineRL-Kit's MOPO as its own code runs it, on one of our datasets, evaluated in Gymnasium v5 (issue 72).

    python experiments/peers/offlinerlkit_mopo.py --kit PATH/TO/OfflineRL-Kit --dataset FILE.hdf5 --task hopper-medium-v2 \\
        --out DIR -- --seed 4 --rollout-length 5 --penalty-coef 5.0 --epoch 200

``--kit`` is a checkout of https://github.com/yihaosun1124/OfflineRL-Kit (not shipped, not installed here: the user
fetches it). Nothing of it is copied or changed: its ``run_example/run_mopo.py`` is imported and its ``train()`` called
with the arguments after ``--`` (its own defaults otherwise). What is supplied from outside is what the issue allows,
loading our HDF5 and evaluating in Gymnasium v5:

* the kit imports ``gym`` and ``d4rl`` (pre-Gymnasium); here they are stand-in modules, and ``gym.make(task)`` returns
  the Gymnasium v5 env of the dataset (``--env``, default the file's own) behind the old API (``reset() -> obs``,
  ``step() -> (obs, reward, done, info)`` with ``done = terminated or truncated``, ``seed(s)`` for the next reset) with
  ``get_normalized_score(return)`` on the data's own reference returns, as our evaluations normalise;
* ``qlearning_dataset(env)`` returns the file's transitions as the kit's dict of arrays (``observations``,
  ``actions``, ``next_observations``, ``rewards``, ``terminals``: the true terminations, not time limits).

The kit's ``--task`` picks its termination function and names its logs: give the D4RL name of the same environment
and level (``hopper-medium-v2``, ``halfcheetah-medium-expert-v2``); its logs go to ``--out`` (``<out>/log/<task>/...``:
the progress CSV holds ``eval/normalized_episode_reward`` per epoch, from the kit's own ``--eval_episodes`` episodes).

Our evaluation, on the policy the kit ends with: ``--final-episodes`` (default 30, as our runs' evaluations) episodes
in the same Gymnasium env, acting with the kit's ``select_action(obs, deterministic=True)``, episode ``i`` reset with
seed ``eval_seed(seed) + i`` (the kit's ``--seed``), normalised with the data's reference returns; written to
``<out>/final_eval.json`` (per-episode returns and lengths, the normalised mean). The policy is taken from the kit's
trainer when its ``train()`` returns (its method is wrapped, not changed).
"""
from __future__ import annotations

import argparse
import os
import sys
import types
from pathlib import Path

import numpy as np

from torchrl_offhrl.data import load_dataset
from torchrl_offhrl.recipes.train import eval_seed
from torchrl_offhrl.scores import normalized_score
from torchrl_offhrl.utils import write_json


class OldApiEnv:
    """A Gymnasium env behind gym's pre-0.26 API, as the kit's trainer calls it, with D4RL's ``get_normalized_score``."""

    def __init__(self, env_id: str, ref: tuple[float, float]):
        import gymnasium

        self._env, self._env_id = gymnasium.make(env_id), env_id
        self.observation_space, self.action_space = self._env.observation_space, self._env.action_space
        self._ref, self._next_seed = ref, None

    def seed(self, seed: int) -> None:
        self._next_seed = int(seed)  # the next reset's; the env's own generator goes on from there

    def reset(self):
        obs, _ = self._env.reset(seed=self._next_seed)
        self._next_seed = None
        return obs

    def step(self, action):
        obs, reward, terminated, truncated, info = self._env.step(action)
        return obs, reward, bool(terminated or truncated), info

    def get_normalized_score(self, ret: float) -> float:
        return normalized_score(self._env_id, ret, self._ref) / 100.0  # D4RL's API: a fraction


def transitions(data) -> dict[str, np.ndarray]:
    """Our dataset's transitions as the kit's ``qlearning_dataset`` dict (terminals: true terminations only)."""
    td = data.data
    return {"observations": td["observation"].numpy(), "actions": td["action"].numpy(),
            "next_observations": td["next", "observation"].numpy(), "rewards": td["next", "reward"].reshape(-1).numpy(),
            "terminals": td["next", "terminated"].reshape(-1).numpy().astype(np.float32)}


def stand_in_modules(make) -> None:
    """``gym`` (``make``, and the names the kit's annotations read) and ``d4rl`` as modules of our own."""
    gym = types.ModuleType("gym")
    gym.make, gym.Env = make, object
    gym.spaces = types.SimpleNamespace(Space=object)
    envs, mujoco = types.ModuleType("gym.envs"), types.ModuleType("gym.envs.mujoco")
    mujoco.mujoco_env = types.SimpleNamespace(MujocoEnv=object)
    gym.envs, envs.mujoco = envs, mujoco
    sys.modules.update({"gym": gym, "gym.envs": envs, "gym.envs.mujoco": mujoco, "d4rl": types.ModuleType("d4rl")})


def final_evaluation(policy, env_id: str, ref: tuple[float, float], seed: int, episodes: int) -> dict:
    """``episodes`` deterministic episodes of the kit's ``policy`` in ``env_id`` (Gymnasium), episode ``i`` reset with
    seed ``eval_seed(seed) + i``; returns, lengths and the normalised mean return (x100, as our pages and the kit)."""
    import gymnasium

    env = gymnasium.make(env_id)
    returns, lengths = [], []
    policy.eval()
    for i in range(episodes):
        obs, _ = env.reset(seed=eval_seed(seed) + i)
        total, steps, done = 0.0, 0, False
        while not done:
            action = policy.select_action(obs.reshape(1, -1), deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action.flatten())
            total, steps, done = total + float(reward), steps + 1, terminated or truncated
        returns.append(total)
        lengths.append(steps)
    return {"env": env_id, "seed": seed, "episodes": episodes, "returns": returns, "lengths": lengths,
            "normalized_mean": normalized_score(env_id, float(np.mean(returns)), ref)}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ours, theirs = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kit", type=Path, required=True, help="a checkout of OfflineRL-Kit")
    ap.add_argument("--dataset", type=Path, required=True, help="one of our HDF5 datasets (or any D4RL-layout file)")
    ap.add_argument("--task", required=True, help="the D4RL name of the same env and level, e.g. hopper-medium-v2")
    ap.add_argument("--env", default=None, help="the Gymnasium env to evaluate in (default: the dataset's own)")
    ap.add_argument("--out", type=Path, required=True, help="where the kit writes its logs")
    ap.add_argument("--final-episodes", type=int, default=30, help="episodes of our evaluation of the kit's last policy (0: none)")
    a = ap.parse_args(ours)
    a.out = a.out.resolve()  # the kit runs in it (chdir below)
    runner = a.kit / "run_example" / "run_mopo.py"
    if not runner.is_file():
        raise SystemExit(f"{a.kit} is not a checkout of OfflineRL-Kit ({runner} is missing): fetch "
                         "https://github.com/yihaosun1124/OfflineRL-Kit and pass its folder as --kit")
    data = load_dataset(a.dataset)
    env_id = a.env or data.metadata.get("env_id")
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    if env_id is None or None in ref:
        raise SystemExit(f"{a.dataset}: no env id or reference returns in its metadata; pass --env (and use a dataset made "
                         "by `offhrl collect`, whose metadata carry the random and expert returns)")
    stand_in_modules(lambda task, **kwargs: OldApiEnv(env_id, ref))
    sys.path[:0] = [str(a.kit), str(a.kit / "run_example")]
    a.out.mkdir(parents=True, exist_ok=True)
    os.chdir(a.out)  # the kit logs under its working directory
    sys.argv = ["run_mopo.py", "--task", a.task, *theirs]  # the kit parses its arguments when its module is imported
    run_mopo = __import__("run_mopo")
    run_mopo.qlearning_dataset = lambda env, *args, **kwargs: transitions(data)
    trainer_cls, kept = run_mopo.MBPolicyTrainer, {}
    own_train = trainer_cls.train

    def train_and_keep(self, *args, **kwargs):
        out = own_train(self, *args, **kwargs)
        kept["policy"] = self.policy
        return out

    trainer_cls.train = train_and_keep
    kit_args = run_mopo.get_args()
    try:
        run_mopo.train(kit_args)
    finally:
        trainer_cls.train = own_train
    if a.final_episodes > 0 and "policy" in kept:
        result = final_evaluation(kept["policy"], env_id, ref, int(kit_args.seed), a.final_episodes)
        result["kit_args"] = {k: v for k, v in vars(kit_args).items() if isinstance(v, (int, float, str, bool, list, type(None)))}
        write_json(a.out / "final_eval.json", result)
        print(f"our evaluation of the kit's last policy ({a.final_episodes} episodes): {result['normalized_mean']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
