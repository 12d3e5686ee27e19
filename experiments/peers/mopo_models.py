"""Our MOPO model and OfflineRL-Kit's, fitted on the same data: how wrong each is where it matters, and whether MOPO's
penalty says so (issue 72).

    python experiments/peers/mopo_models.py --ours CACHE/models/<id>/ensemble.pt \\
        [--kit-checkout PATH/TO/OfflineRL-Kit --kit-model DIR] [--run RUN_DIR] [--env hopper] [--transitions 20000] \\
        [--seed 99] [--episodes 30] [--out FILE.json]

``--ours``: our Gaussian ensemble (``algo=mopo``'s, ``ensemble.loss=nll``, elites kept); ``--kit-model``: the folder
where the kit saved its dynamics (``dynamics.pth``, ``mu.npy``, ``std.npy``: ``<kit>/<dataset>/dynamics/`` as
``mopo_side_by_side.py`` keeps it), rebuilt with the kit's own classes and its ``run_mopo.py`` defaults (7 members of
4 x 200, 5 elites), imported from ``--kit-checkout``, nothing copied. Each model is scored on real transitions neither
saw (a simulator is fine here: the question is asked while building the library, not by a user):

* ``behaviour``: fresh ``medium`` transitions of ``--env`` from dataset seed ``--seed`` (no training set used it);
* ``policy``: the real transitions of a trained policy (``--run``: a run's last policy, rolled out for ``--episodes``
  first episodes in the real env), the states the policy leads to, where a MOPO policy that exploits its model goes.

Per model and set it prints: the error of the elites' mean next state (L2 norm, the state's units), MOPO's penalty
(the largest L2 norm over the elites of the predicted standard deviation of state and reward: the kit's ``aleatoric``
mode, our ``model_env.discrepancy=aleatoric``), their rank correlation (Spearman), the share of transitions whose
error exceeds the penalty, the reward's real mean with the elites' mean prediction's bias and absolute error, and on Hopper the share of the real falls (a next state the task ends on) that the elites'
mean also predicts as a fall: a model that does not predict the falls keeps a falling policy up in its rollouts. With
``--run``, last, the policy closed loop in each model from the real episodes' start states (the elites' mean state and
reward each step, the task's termination): how long the model keeps up what the real env lets fall; and what the run's
own critic (twin Q, SAC's) says of its last policy at the real start states, one step before each real fall, and at
dataset states, beside the real returns there.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from torchrl_offhrl.envs import termination_fn_for
from torchrl_offhrl.utils import write_json


def _ours(path: str):
    from torchrl_offhrl.models import DynamicsEnsemble

    model = DynamicsEnsemble.load(path)

    @torch.no_grad()
    def predict(obs: torch.Tensor, act: torch.Tensor):
        out = model.predict(obs, act, chunk=4096)
        if out["std"] is None:
            raise SystemExit(f"{path}: not a Gaussian ensemble (fitted with ensemble.loss={model.loss_type}); MOPO's penalty needs loss=nll")
        return out["next_observation"], out["reward"], out["std"]

    return predict


def _kit(checkout: str, folder: str, obs_dim: int, act_dim: int):
    sys.path.insert(0, str(Path(checkout).resolve()))
    from offlinerlkit.modules import EnsembleDynamicsModel
    from offlinerlkit.utils.scaler import StandardScaler

    model = EnsembleDynamicsModel(obs_dim=obs_dim, action_dim=act_dim, hidden_dims=[200, 200, 200, 200], num_ensemble=7, num_elites=5,
                                  weight_decays=[2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4], device="cpu")
    model.load_state_dict(torch.load(Path(folder) / "dynamics.pth", map_location="cpu", weights_only=True))  # a state dict: tensors only
    model.eval()
    scaler = StandardScaler()
    scaler.load_scaler(folder)
    elites = model.elites.data.cpu().long()

    @torch.no_grad()
    def predict(obs: torch.Tensor, act: torch.Tensor):
        x = scaler.transform(np.concatenate([obs.numpy(), act.numpy()], -1))
        mean, logvar = model(x)  # [E, N, obs + 1]: the state's change and the reward, raw units
        mean, std = mean[elites].cpu(), (0.5 * logvar[elites]).exp().cpu()
        return obs + mean[..., :-1], mean[..., -1], std

    return predict


def _spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def score(predict, obs, act, next_obs, reward, terminated, env_id: str) -> dict:
    """The numbers of one model on one set of real transitions (see the module's docstring)."""
    pred_next, pred_reward, std = predict(obs, act)
    mean_next = pred_next.mean(0)
    err = (mean_next - next_obs).norm(dim=-1)
    pen = std.norm(dim=-1).amax(0)
    r_err = pred_reward.mean(0) - reward
    out = {"transitions": int(obs.shape[0]), "error_mean": float(err.mean()), "error_q90": float(err.quantile(0.9)),
           "reward_bias": float(r_err.mean()), "reward_abs_error": float(r_err.abs().mean()), "reward_mean": float(reward.mean()),
           "penalty_mean": float(pen.mean()), "penalty_q90": float(pen.quantile(0.9)), "spearman": _spearman(err, pen),
           "error_above_penalty": float((err > pen).double().mean())}
    falls = terminated.bool()
    if falls.any():
        predicted = termination_fn_for(env_id)(mean_next)
        out.update(real_falls=int(falls.sum()), falls_predicted=float(predicted[falls].double().mean()),
                   false_falls=float(predicted[~falls].double().mean()))
    return out


def behaviour_set(env: str, n: int, seed: int):
    from torchrl_offhrl.data import generate_dataset

    data = generate_dataset(env, "medium", num_transitions=n, seed=seed, progress=False)
    td = data.data
    return (td["observation"], td["action"], td["next", "observation"], td["next", "reward"].reshape(-1), td["next", "terminated"].reshape(-1),
            data.metadata.get("env_id"))


def policy_set(run: str, episodes: int):
    from torchrl_offhrl.recipes.evaluation import load_run_agent
    from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask

    cfg, env, agent, _, _ = load_run_agent(run, num_envs=episodes, policy="last")
    returns, ro = evaluate_policy(env, agent.eval_policy, episodes, max_steps=1000, seed=12345, return_rollout=True)
    alive = first_episode_mask(ro["next", "done"].reshape(episodes, -1))
    critic = critic_probe(cfg, agent, ro, alive, episodes)
    obs, act = ro["observation"][alive], ro["action"][alive]
    env.close()
    lengths = alive.sum(1)
    start = ro["observation"].reshape(episodes, -1, obs.shape[-1])[:, 0]
    return (obs, act, ro["next", "observation"][alive], ro["next", "reward"].reshape(episodes, -1)[alive],
            ro["next", "terminated"].reshape(episodes, -1)[alive], cfg["env"]["env_id"], returns, (agent.eval_policy, start, lengths, agent.action_key),
            critic)


@torch.no_grad()
def critic_probe(cfg: dict, agent, ro, alive: torch.Tensor, episodes: int, gamma: float = 0.99) -> dict | None:
    """What a SAC-family run's critic says of its last policy, ``min_i Q_i(s, pi(s))`` (medians), where the real env shows the
    answer: at the real episodes' start states (beside the real discounted return from there), one step before each real
    fall (the real return from there: that step's reward), and at 2,000 of the dataset's states. None without twin Q."""
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_offhrl.recipes.config import resolve_dataset

    loss = agent.loss
    if not hasattr(loss, "qvalue_network_params"):
        return None

    def q(obs):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            act = agent.eval_policy(TensorDict(observation=obs, batch_size=[obs.shape[0]]))[agent.action_key]
        td = TensorDict({"observation": obs, agent.action_key: act}, batch_size=[obs.shape[0]])
        values = []
        for i in range(loss.qvalue_network_params.shape[0]):
            with loss.qvalue_network_params[i].to_module(loss.qvalue_network):
                values.append(loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1))
        return torch.stack(values).min(0).values

    obs = ro["observation"].reshape(episodes, -1, ro["observation"].shape[-1])
    lengths = alive.sum(1)
    rew = (ro["next", "reward"].reshape(episodes, -1) * alive).double()
    discounted = (rew * gamma ** torch.arange(rew.shape[1], dtype=torch.float64)).sum(1)
    data = resolve_dataset(cfg).data["observation"]
    states = data[torch.randint(len(data), (2000,), generator=torch.Generator().manual_seed(0))]
    # one step before each real fall: the last step of the first episodes that ended by termination (not by the time limit)
    last = lengths - 1
    fell = ro["next", "terminated"].reshape(episodes, -1)[torch.arange(episodes), last].bool()
    fall_rows = torch.arange(episodes)[fell]
    before_fall = obs[fall_rows, last[fell]]
    return {"q_start": float(q(obs[:, 0]).median()), "real_discounted_return_start": float(discounted.median()),
            "falls": int(fell.sum()),
            "q_before_fall": float(q(before_fall).median()) if len(fall_rows) else None,
            "reward_at_fall": float(rew[fall_rows, last[fell]].median()) if len(fall_rows) else None,
            "q_dataset_states": float(q(states).median())}


@torch.no_grad()
def closed_loop(predict, policy, start: torch.Tensor, env_id: str, steps: int = 1000, action_key: str = "action") -> dict:
    """The policy rolled out in the model from the real episodes' start states: each step the elites' mean next state and
    reward (no sampling), ended where the task's termination says; the lengths and returns, per episode."""
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    term = termination_fn_for(env_id)
    obs, n = start.clone(), start.shape[0]
    alive, length, ret = torch.ones(n, dtype=torch.bool), torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.float64)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(steps):
            act = policy(TensorDict(observation=obs, batch_size=[n]))[action_key]
            nxt, rew, _ = predict(obs, act)
            nxt, rew = nxt.mean(0), rew.mean(0)
            length += alive.long()
            ret += torch.where(alive, rew.double(), torch.zeros_like(ret))
            alive = alive & ~term(nxt)
            if not alive.any():
                break
            obs = nxt
    return {"lengths": length.tolist(), "returns": [round(float(r), 1) for r in ret]}


def markdown_tables(result: dict) -> list[str]:
    """The printed (and paged: ``mopo_side_by_side.py``) tables of a result."""
    lines = ["| model | set | transitions | state error (mean, q90) | penalty (mean, q90) | Spearman | error > penalty | reward: real "
             "mean, model bias, abs error | real falls predicted | false falls |", "|---|---|---|---|---|---|---|---|---|---|"]
    for m, by_set in result["models"].items():
        for s in result["sets"]:
            if s not in by_set:  # a model measured on fewer sets (added to a result after its runs' folders were gone)
                lines.append(f"| {m} | {s} | not measured | | | | | | | |")
                continue
            r = by_set[s]
            falls = f"{r['falls_predicted']:.2f} of {r['real_falls']}" if "real_falls" in r else "n/a"
            false = f"{r['false_falls']:.3f}" if "false_falls" in r else "n/a"
            lines.append(f"| {m} | {s} | {r['transitions']} | {r['error_mean']:.3f}, {r['error_q90']:.3f} | {r['penalty_mean']:.3f}, "
                         f"{r['penalty_q90']:.3f} | {r['spearman']:.2f} | {r['error_above_penalty']:.2f} | {r['reward_mean']:.2f}, "
                         f"{r['reward_bias']:+.3f}, {r['reward_abs_error']:.3f} | {falls} | {false} |")
    lines += [""] + [f"- `{k}`: {v}" for k, v in result["sets"].items()]
    if result.get("real_episodes"):
        med = lambda xs: float(np.median(xs))  # noqa: E731
        lines += ["", "Each run's last policy from its real episodes' start states, closed loop (the elites' mean state and reward, no "
                  "sampling, the task's termination): episode length, median [min, max], and median return.", "",
                  "| policy | real env | " + " | ".join({'ours': 'our model', 'kit': "the kit's model"}.get(m, m) for m in result["models"]) + " |",
                  "|---|---|" + "---|" * len(result["models"])]
        for s, real in result["real_episodes"].items():
            cells = [f"{med(real['lengths']):.0f} [{min(real['lengths'])}, {max(real['lengths'])}], {med(real['returns']):.1f}"]
            for m in result["models"]:
                c = result["models"][m].get("closed_loop", {}).get(s)
                cells.append("not measured" if c is None else
                             f"{med(c['lengths']):.0f} [{min(c['lengths'])}, {max(c['lengths'])}], {med(c['returns']):.1f}")
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
    if result.get("critic"):
        lines += ["", "What each run's critic says of its last policy (the smaller of its twin Q-values at the policy's action, median; "
                  "gamma 0.99, the run's reward scale) where the real env gives the answer:", "",
                  "| policy | Q at the real start states | the real discounted return from there | Q one step before the real fall "
                  "| the real reward of that step | Q at 2,000 dataset states |", "|---|---|---|---|---|---|"]
        for s, c in result["critic"].items():
            if c["q_before_fall"] is None:  # no first episode ended by termination (HalfCheetah never does)
                fall = "n/a (no real fall) | n/a"
            else:
                fall = f"{c['q_before_fall']:.1f} | {c['reward_at_fall']:.2f}"
            lines.append(f"| {s} | {c['q_start']:.1f} | {c['real_discounted_return_start']:.1f} | {fall} | {c['q_dataset_states']:.1f} |")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ours", required=True)
    p.add_argument("--kit-checkout")
    p.add_argument("--kit-model")
    p.add_argument("--run", nargs="*", default=[], help="runs whose last policies give the 'policy' sets (one per run)")
    p.add_argument("--env", default="hopper")
    p.add_argument("--transitions", type=int, default=20000)
    p.add_argument("--seed", type=int, default=99)
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--out")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    sets, loops = {}, {}
    obs, act, nxt, rew, term, env_id = behaviour_set(a.env, a.transitions, a.seed)
    sets["behaviour"] = (obs, act, nxt, rew, term)
    result = {"env_id": env_id, "sets": {"behaviour": f"{a.transitions} fresh medium transitions, dataset seed {a.seed}"}, "models": {},
              "real_episodes": {}}
    for run in a.run:
        name = f"policy {Path(run).name}"
        obs_p, act_p, nxt_p, rew_p, term_p, _, returns, loops[name], critic = policy_set(run, a.episodes)
        if critic is not None:
            result.setdefault("critic", {})[name] = critic
        lengths = loops[name][2]
        result["real_episodes"][name] = {"lengths": lengths.tolist(), "returns": [round(float(r), 1) for r in returns]}
        sets[name] = (obs_p, act_p, nxt_p, rew_p, term_p)
        result["sets"][name] = f"the last policy of {Path(run).name}, {a.episodes} first episodes in the real env, mean return {float(returns.mean()):.1f}"
    models = {"ours": _ours(a.ours)}
    if a.kit_model:
        if not a.kit_checkout:
            raise SystemExit("--kit-model needs --kit-checkout (the kit's classes rebuild its model)")
        models["kit"] = _kit(a.kit_checkout, a.kit_model, obs.shape[-1], act.shape[-1])
    for m, predict in models.items():
        result["models"][m] = {s: score(predict, o, ac, n, rw, t, env_id) for s, (o, ac, n, rw, t) in sets.items()}
        result["models"][m]["closed_loop"] = {s: closed_loop(predict, policy, start, env_id, action_key=key)
                                            for s, (policy, start, _, key) in loops.items()}
    print("\n".join(markdown_tables(result)))
    if a.out:
        write_json(a.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
