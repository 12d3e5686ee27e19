"""Evaluation in the real Gymnasium env: during training (:class:`Evaluator`) and of a saved run (:func:`evaluate_run`, optional frames).

Always deterministic during training, through the same decoder the agent
trained with, on ``episodes`` parallel envs seeded the same way at every
evaluation, so the learning curve compares like with like.
"""
from __future__ import annotations

from pathlib import Path

import torch

from ..agents import agent_class, make_agent
from ..registry import task_of
from ..models import ClonedPolicy, ConditionalVAE
from ..rollouts import evaluate_policy, first_episode_mask
from ..scores import normalized_score
from ..utils import load_torch_file
from .config import (acts_in_latent_space, latent_bound, model_config, model_env_config, offline_rules_for, resolve_dataset, transfer_config,
                     upgrade_config)
from .pipeline import apply_latent_origin, fit_or_load_models, make_eval_model_env, make_real_env, origin_path, origin_share
from .runs import read_json

__all__ = ["Evaluator", "GoalEvaluator", "RunModels", "SeedsEvaluation", "acting_task", "evaluate_run", "load_run_agent", "render_episode", "run_models"]


class Evaluator:
    """Deterministic real-env evaluation of an agent, as one JSON-able record.

    Args:
        env: the batched real env (``batch_size=[episodes]``) with the agent's
            transforms appended.
        env_id: for the D4RL-normalised score.
        episodes, max_steps, seed: the evaluation protocol (the same seed at
            every evaluation).
        ref: ``(random, expert)`` returns of the dataset's own references, or None.
        model_env: the pessimistic model env (``batch_size=[episodes]``, the
            agent's transforms appended), or None. With it, each evaluation also
            rolls the same deterministic policy out in the model from dataset
            start states: ``model_return_mean`` / ``_std`` and
            ``model_real_gap`` (model minus real mean return; an agent that
            exploits model errors shows a large positive gap). The global RNG
            is restored afterwards, so training is not changed by it.
        sampled: also evaluate the *sampled* policy (actions and options
            drawn, ``eval.sampled``) on the same start states:
            ``return_mean_sampled`` / ``return_std_sampled`` /
            ``normalized_d4rl_sampled``. It draws from its own RNG stream,
            so training is not changed by it.
        task: the task the env rewards (transfer runs: ``"forward"`` or
            ``"backward"``, written into each record), or None (an offline
            run: no ``task`` key). D4RL's normalisation is defined for the
            forward task only: on another task ``normalized_*`` are None.

    ``evaluator(agent)`` returns ``return_mean``, ``return_std``,
    ``normalized_d4rl``, ``normalized_dataset`` and the agent's
    :meth:`~torchrl_offhrl.agents.Agent.evaluation_metrics`; with
    ``save_to=run_dir`` it also has the agent write its evaluation files.
    """

    def __init__(self, env, env_id: str, episodes: int, max_steps: int, seed: int, ref=None, model_env=None, task: str | None = None,
                 gamma: float = 0.99, sampled: bool = False):
        self.env, self.env_id, self.episodes, self.max_steps, self.seed, self.ref = env, env_id, episodes, max_steps, seed, ref
        self.model_env = model_env
        self.task = task
        self.gamma = float(gamma)
        self.sampled = bool(sampled)
        self.prepared = None  # rollouts made elsewhere for the next call (SeedsEvaluation), used once

    def rollouts(self, agent) -> tuple:
        """``(returns, rollout, sampled returns or None)``: the deterministic evaluation's first-episode returns ``[episodes]``
        and its ``[episodes, T]`` rollout, and the sampled policy's returns on the same start states (``sampled``)."""
        rets, td = evaluate_policy(
            self.env, agent.eval_policy, self.episodes, max_steps=self.max_steps, deterministic=True, seed=self.seed, return_rollout=True,
        )
        srets = None
        if self.sampled:  # the stochastic policy on the same start states (evaluate_policy forks the RNG for its draws)
            srets = evaluate_policy(self.env, agent.eval_policy, self.episodes, max_steps=self.max_steps, deterministic=False, seed=self.seed)
        return rets, td, srets

    def __call__(self, agent, save_to: Path | None = None, title: str = "") -> dict:
        prepared, self.prepared = self.prepared, None
        rets, td, srets = prepared if prepared is not None else self.rollouts(agent)
        mean = float(rets.mean())
        forward = self.task in (None, "forward")
        rec = {} if self.task is None else {"task": self.task}
        rec.update({
            "return_mean": mean,
            "return_std": float(rets.std()),
            "normalized_d4rl": normalized_score(self.env_id, mean) if forward else None,
            "normalized_dataset": normalized_score(self.env_id, mean, ref=self.ref) if self.ref and forward else None,
        })
        if srets is not None:
            smean = float(srets.mean())
            rec.update({"return_mean_sampled": smean, "return_std_sampled": float(srets.std()),
                        "normalized_d4rl_sampled": normalized_score(self.env_id, smean) if forward else None})
        rec.update(self.model_metrics(agent, mean))
        alive = first_episode_mask(td["next", "done"].reshape(self.episodes, -1))
        rec.update(agent.evaluation_metrics(td, alive))
        if save_to is not None:
            Path(save_to).mkdir(parents=True, exist_ok=True)
            agent.save_evaluation(td, alive, Path(save_to), title)
        return rec

    def model_metrics(self, agent, real_mean: float) -> dict:
        """The same deterministic policy in the pessimistic model env (if any): a large model-real gap means it exploits model errors.

        Besides the mean return: ``model_return_min_member``, the mean return
        of the ensemble member under which the policy does worst (a lower
        confidence bound over the ensemble; with a ``member_draw="cyclic"``
        env every member gets the same episodes' start states);
        ``model_discounted_mean`` / ``model_discounted_min_member``, the same
        for the return discounted with ``gamma`` (the agent's own objective);
        where model episodes end: ``model_episode_length_mean`` (steps),
        ``model_penalized``, the share ended by the pessimism, and
        ``model_terminated``, the share ended by the task's own terminal states
        (a fall; the rest ran to the model env's horizon or ``max_steps``): a
        model whose episodes end much earlier than the data's trains the agent
        on another problem than the one it is evaluated on;
        and ``model_episode_returns`` / ``model_episode_members``,
        every episode's return and member (the guard pairs them with the
        start policy's). Offline policy selection
        (:class:`~torchrl_offhrl.recipes.selection.PolicySelector`) reads them.
        """
        if self.model_env is None:
            return {}
        n = self.model_env.batch_size.numel()
        with torch.random.fork_rng():
            model_rets, td = evaluate_policy(self.model_env, agent.eval_policy, n, max_steps=self.max_steps, deterministic=True, seed=self.seed,
                                             return_rollout=True)
        m = float(model_rets.mean())
        out = {"model_return_mean": m, "model_return_std": float(model_rets.std()), "model_real_gap": m - real_mean}
        alive = first_episode_mask(td["next", "done"].reshape(n, -1))
        reward = td["next", "reward"].reshape(n, -1).double().cpu()
        disc = (reward * alive.cpu() * self.gamma ** torch.arange(reward.shape[1], dtype=torch.float64)).sum(1)
        out["model_discounted_mean"] = float(disc.mean())
        if "model_member" in td.keys():
            member = td["model_member"][:, 0].reshape(-1).cpu()
            members = member.unique()

            def worst_member(per_episode):  # the mean over each member's episodes, the lowest of them
                return min(float(per_episode[member == k].mean()) for k in members)

            out["model_return_min_member"] = worst_member(model_rets.double())
            out["model_discounted_min_member"] = worst_member(disc)
            # per episode, to pair two policies' evaluations episode by episode (the guard: selection.paired_gain_lcb)
            out["model_episode_returns"] = [round(float(x), 4) for x in model_rets.double()]
            out["model_episode_members"] = [int(x) for x in member]
        out["model_episode_length_mean"] = float(alive.sum(1).double().mean())
        penalized = td["next", "penalized"].reshape(n, -1) & alive if ("next", "penalized") in td.keys(True) else None
        if penalized is not None:
            out["model_penalized"] = float(penalized.any(1).float().mean())
        if ("next", "terminated") in td.keys(True):
            task_end = td["next", "terminated"].reshape(n, -1) & alive & (~penalized if penalized is not None else True)
            out["model_terminated"] = float(task_end.any(1).float().mean())
        return out


class SeedsEvaluation:
    """The real-env evaluations of N seeds' runs (a seeds' batch, :mod:`~torchrl_offhrl.recipes.seed_runs`) as one rollout.

    ``env`` holds the N runs' evaluation envs as blocks of ``episodes`` envs (seed ``i``'s block: envs
    ``i * episodes .. (i + 1) * episodes - 1``), each block seeded as its run's own evaluation env is
    (:func:`~torchrl_offhrl.rollouts.seed_each_env`: run ``i``'s ``evaluators[i].seed + j`` for its env ``j``), so
    every seed's episodes start from its own run's start states. :meth:`prepare` rolls the N policies out as one
    vmapped :class:`~torchrl_offhrl.agents.seeds.SeedBatchedPolicy` (deterministic, then sampled when the runs
    evaluate it) and hands each run's evaluator its block (:attr:`Evaluator.prepared`); the evaluator then makes its
    record as it would from its own rollouts, the model-env part included (that part runs per seed).

    Each seed's deterministic episodes are its own policy's from its own start states; they can differ from a
    separate run's in floating-point rounding (a vmapped matrix product is not the same kernel), which a long
    episode of a chaotic system amplifies, so a batched run's evaluations are those of the same policy, not
    bit-for-bit replays. The sampled policy's draws come from the batch's own seeded stream
    (``seed``), each seed its own (``randomness="different"``), not from the runs' own.

    Args:
        evaluators: the N runs' :class:`Evaluator` (one protocol: episodes, max_steps, sampled).
        env: the real env of ``N * episodes`` envs with the agents' transforms (``Setting.eval_env_for(N)``).
        seed: seeds the sampled evaluation's draws.
    """

    def __init__(self, evaluators, env, seed: int):
        evs = list(evaluators)
        if any(type(ev) is not Evaluator for ev in evs):
            raise TypeError("SeedsEvaluation batches plain Evaluators (returns), not per-goal or other evaluations")
        first = evs[0]
        if any((ev.episodes, ev.max_steps, ev.sampled) != (first.episodes, first.max_steps, first.sampled) for ev in evs):
            raise ValueError("the seeds' evaluations differ in episodes, max_steps or sampled: they cannot share a rollout")
        if env.batch_size.numel() != len(evs) * first.episodes:
            raise ValueError(f"SeedsEvaluation: env of batch size {tuple(env.batch_size)} for {len(evs)} runs x {first.episodes} episodes")
        self.evaluators, self.env, self.seed = evs, env, int(seed)
        self.env_seeds = [ev.seed + j for ev in evs for j in range(ev.episodes)]

    def prepare(self, policies) -> None:
        """Roll the N runs' policies (their :attr:`~torchrl_offhrl.agents.Agent.eval_policy`, one per evaluator, of one
        architecture) out together; each evaluator's next call makes its record from its block."""
        from ..agents.seeds import SeedBatchedPolicy, stacked_module_params

        policies = list(policies)
        if len(policies) != len(self.evaluators):
            raise ValueError(f"{len(policies)} policies for {len(self.evaluators)} runs")
        policy = SeedBatchedPolicy(policies[0], stacked_module_params(policies))
        first, n = self.evaluators[0], len(self.evaluators)
        total = n * first.episodes
        with torch.random.fork_rng():  # the caller's stream (the batch's training draws) is left as it was
            rets, td = evaluate_policy(self.env, policy, total, max_steps=first.max_steps, deterministic=True, seed=self.seed,
                                       env_seeds=self.env_seeds, return_rollout=True)
        srets = None
        if first.sampled:
            srets = evaluate_policy(self.env, policy, total, max_steps=first.max_steps, deterministic=False, seed=self.seed, env_seeds=self.env_seeds)
        e = first.episodes
        for i, ev in enumerate(self.evaluators):
            block = slice(i * e, (i + 1) * e)
            ev.prepared = (rets[block], td[block], None if srets is None else srets[block])

    def discard(self) -> None:
        """Drop what :meth:`prepare` handed out and no evaluation used."""
        for ev in self.evaluators:
            ev.prepared = None

    def close(self) -> None:
        self.env.close()


class GoalEvaluator(Evaluator):
    """Per-goal success on a goal-conditioned task (block stacking), as UOF tests: ``episodes`` episodes of every goal.

    ``env`` is the batched real env with ``episodes * num_goals`` copies, copy
    ``i`` fixed to goal ``i // episodes``
    (:func:`~torchrl_offhrl.blockstack.make_blockstack_env` with ``goals=``)
    and a time limit of ``max_steps`` (UOF tests with 50), the agent's
    transforms appended. One deterministic rollout of ``max_steps`` steps
    gives both horizons: an episode succeeds when its high-level reward is 0 at
    some step (the success flags equal the goal's); within the first
    ``horizon`` steps (25: training's horizon, the paper's) it is
    ``success_rate`` / ``success_per_goal``, within all ``max_steps`` it is
    ``success_rate_h<max_steps>`` / ``success_per_goal_h<max_steps>``
    (nothing in the env depends on the time limit, so the first 25 steps of a
    50-step episode are a 25-step episode). ``return_mean`` is the return over
    the first ``horizon`` steps; there is no D4RL score. The agent's
    :meth:`~torchrl_offhrl.agents.Agent.evaluation_metrics` and evaluation
    files see the first ``horizon`` steps.
    """

    def __init__(self, env, env_id: str, episodes: int, num_goals: int, horizon: int, max_steps: int, seed: int, model_env=None):
        super().__init__(env, env_id, episodes * num_goals, max_steps, seed, model_env=model_env)
        self.per_goal, self.num_goals, self.horizon = int(episodes), int(num_goals), int(horizon)
        if self.horizon > self.max_steps:
            raise ValueError(f"the evaluation's max_steps ({max_steps}) must be at least the training horizon ({horizon})")

    def __call__(self, agent, save_to: Path | None = None, title: str = "") -> dict:
        from ..blockstack.goals import success_by_goal

        _, td = evaluate_policy(self.env, agent.eval_policy, self.episodes, max_steps=self.max_steps, deterministic=True, seed=self.seed, return_rollout=True)
        reward = td["next", "reward"].reshape(self.episodes, -1)
        alive = first_episode_mask(td["next", "done"].reshape(self.episodes, -1))
        goal = td["desired_goal"][:, 0].argmax(-1)
        h = min(self.horizon, reward.shape[1])
        rets = (reward[:, :h] * alive[:, :h]).sum(1)
        short = success_by_goal(reward[:, :h], alive[:, :h], goal, self.num_goals)
        full = success_by_goal(reward, alive, goal, self.num_goals)
        mean = float(rets.mean())
        rec = {"return_mean": mean, "return_std": float(rets.std()), "normalized_d4rl": None, "normalized_dataset": None,
               "success_rate": float(short.nanmean()), "success_per_goal": short.tolist(),
               f"success_rate_h{self.max_steps}": float(full.nanmean()), f"success_per_goal_h{self.max_steps}": full.tolist()}
        rec.update(self.model_metrics(agent, mean))
        head = td[:, :h]
        rec.update(agent.evaluation_metrics(head, alive[:, :h]))
        if save_to is not None:
            Path(save_to).mkdir(parents=True, exist_ok=True)
            agent.save_evaluation(head, alive[:, :h], Path(save_to), title)
        return rec


def acting_task(cfg: dict, state: dict) -> tuple[str, bool]:
    """``(task, decoder discarded)`` of a run's checkpointed agent: a transfer run past its switch acts on the new task."""
    tcfg = transfer_config(cfg)
    online = tcfg is not None and any(r.get("phase") == "online" for r in state.get("records", []))
    if not online:
        return "forward", False
    return tcfg["task"], acts_in_latent_space(cfg) and tcfg["decoder"] == "discard"


class RunModels:
    """A finished run's data, models and model-env settings, as its training resolved them (:func:`run_models`).

    ``cfg`` (the run's ``config.json``), ``data``, ``pcfg`` (:func:`~torchrl_offhrl.recipes.config.model_config` with
    its ``env`` resolved by the offline rules), ``ensemble``, ``cvae`` (as fitted: no latent origin), ``model_dir``
    (the CVAE's cache folder) and ``rules``. :meth:`model_env` builds the run's evaluation model env.
    """

    def __init__(self, cfg: dict, data, pcfg: dict, ensemble, cvae, model_dir, rules):
        self.cfg, self.data, self.pcfg, self.ensemble, self.cvae, self.model_dir, self.rules = cfg, data, pcfg, ensemble, cvae, model_dir, rules

    def model_env(self, cvae=None, batch_size: int | None = None, latent: bool = True, threshold: float | None = None):
        """The run's evaluation model env: ``eval.model_episodes`` episodes (or ``batch_size``) of ``eval.max_steps`` steps
        from the data's start states, member ``i % K`` for episode ``i``, the run's threshold (or ``threshold``); decoding
        through ``cvae`` (e.g. :func:`load_run_agent`'s, with the run's latent origin) when ``latent``."""
        ev = self.cfg["eval"]
        n = batch_size or int(ev.get("model_episodes") or ev["episodes"])
        return make_eval_model_env(self.pcfg, self.ensemble, cvae if latent else None, self.data, n, int(ev["max_steps"]),
                                   float(self.cfg["threshold"] if threshold is None else threshold), latent=latent)


def run_models(run_dir, data=None) -> RunModels:
    """A finished run's data and models from the cache, with the offline rules computed again as its training computed
    them (from the data and the fitted models: the CVAE before its latent origin): to study a finished run offline, e.g.
    roll its saved policies, or a policy of your own, out in the model it was judged in::

        run = "outputs/runs/moc-hopper-medium-seed0"
        _, env, agent, state, cvae = load_run_agent(run)           # its last policy, acting in the real env
        model_env = agent.attach(run_models(run).model_env(cvae))  # the model episodes its evaluations ran
        returns = rollouts.evaluate_policy(model_env, agent.eval_policy, 50, max_steps=1000)
    """
    cfg = upgrade_config(read_json(Path(run_dir) / "config.json"))  # today's key names
    data = resolve_dataset(cfg) if data is None else data
    pcfg = model_config(cfg)
    ensemble, cvae, info = fit_or_load_models(pcfg, data, progress=False)
    rules = offline_rules_for(cfg, data, ensemble, cvae)
    pcfg["env"], _ = model_env_config(cfg, data.metadata.get("level"), data, rules=rules)
    return RunModels(cfg, data, pcfg, ensemble, cvae, Path(cfg.get("model_dir") or info["model_dir"]), rules)


def load_run_agent(run_dir, num_envs: int = 1, policy: str = "last"):
    """``(cfg, env, agent, state, cvae)``: a run's agent rebuilt from ``config.json`` and ``checkpoint.pt``, acting in the real env.

    ``policy="selected"`` loads the policy the run returned by offline policy
    selection (``selected.pt``, :mod:`~torchrl_offhrl.recipes.selection`)
    instead of the last one, where the run has it (else the last one). When
    the guard returned the percentile BC (:mod:`~torchrl_offhrl.recipes.fallback`),
    ``agent`` is that :class:`~torchrl_offhrl.models.ClonedPolicy`
    and ``env`` the real env in real actions.

    The env (``num_envs`` side by side) decodes through the run's CVAE, loaded
    from the model cache (``cvae``, None for a run without it); ``state`` is
    the checkpoint (frames, records, ...). A transfer run checkpointed in its
    online phase acts as it was fine-tuned: on the new task, through the
    affine action map when the decoder was discarded (``cvae`` is then None).
    """
    run = Path(run_dir)
    cfg_path, ckpt_path = run / "config.json", run / "checkpoint.pt"
    for p in (cfg_path, ckpt_path):
        if p.exists() and not p.is_file():
            raise FileNotFoundError(f"{p} is not a regular file (a folder or a device): {run} is not a (checkpointed) run directory "
                                    "of `offhrl train`")
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: {run} is not a (checkpointed) run directory of `offhrl train`")
    cfg = upgrade_config(read_json(cfg_path))  # today's key names, whatever version wrote it
    env_id = cfg["env"]["env_id"]
    latent = acts_in_latent_space(cfg)
    state = load_torch_file(ckpt_path, "run checkpoint", f"its previous checkpoint is {run / 'checkpoint.prev.pt'} (rename it to evaluate that one)")
    task, discard = acting_task(cfg, state)
    cvae = None
    if latent and not discard:
        model_dir = cfg.get("model_dir")
        if model_dir is None and (run / "summary.json").is_file():
            model_dir = read_json(run / "summary.json").get("models")
        if model_dir is None:
            raise FileNotFoundError(f"{cfg_path} does not say which models the run used (written by an older version); train it again")
        cvae_path = Path(model_dir) / "cvae.pt"
        if not cvae_path.is_file():
            raise FileNotFoundError(f"the run's CVAE {cvae_path} is not in the model cache any more; rerun `offhrl fit` with the run's config")
        cvae = ConditionalVAE.load(cvae_path)
    bound = latent_bound(cfg)
    menv = cfg.get("model_env") or {}
    origin = {"latent_origin": menv.get("latent_origin", "zero")}  # runs from before the key decoded latents as they are
    if "origin_share" in menv:
        origin["origin_share"] = menv["origin_share"]
    share = origin_share(origin)
    if cvae is not None and share is not None:
        data = None
        if not origin_path(model_dir, share).is_file():  # fitted again from the run's data (deterministic: its seed)
            print(f"the run's latent origin is not in the model cache ({model_dir}): fitting it again from the run's data")
            data = resolve_dataset(cfg)
        apply_latent_origin({**model_config(cfg), "env": {**origin, "latent_bound": bound}}, data, cvae, model_dir, progress=False)
    env = make_real_env(env_id, cvae, num_envs=num_envs, latent_bound=bound, task=task, discard_decoder=discard)
    algo = dict(cfg["algo"])
    if isinstance(algo.get("reward_scale"), str):  # a name resolved from the data at training time (e.g. IQL's return_range)
        algo["reward_scale"] = float(cfg.get("resolved_reward_scale") or 1.0)
    goal_key = "sub_goal" if task_of(env_id).goal_conditioned else None  # as the loop built it
    # built to act in the real env, not to collect on the model env: its training schedule's keys are left out (MOPO's)
    algo = {k: v for k, v in algo.items() if k not in agent_class(algo["name"]).training_only_keys}
    agent = make_agent(algo["name"], env, algo, action_key="latent_action" if latent else "action", goal_key=goal_key)
    agent.attach(env)
    if policy not in ("last", "selected"):
        raise ValueError(f"policy must be 'last' or 'selected', got {policy!r}")
    if policy == "selected" and (run / "selected.pt").is_file():
        chosen = load_torch_file(run / "selected.pt", "selected policy", "rerun the training command to write it again")
        if chosen.get("policy") == "percentile_bc":  # the guard returned the percentile BC: it acts in real actions, no decoder
            env.close()
            return cfg, make_real_env(env_id, None, num_envs=num_envs, task=task), ClonedPolicy.from_state(chosen["bc"]), {**state, "frames": 0}, cvae
        agent.load_state_dict(chosen["agent"])
        state = {**state, "frames": int(chosen["record"]["frames"])}
    else:
        agent.load_state_dict(state["agent"])
    return cfg, env, agent, state, cvae


def evaluate_run(run_dir, episodes: int = 10, seed: int = 12345, frames_dir=None, deterministic: bool = True, policy: str = "selected") -> dict:
    """Evaluate a run's policy in the real env: returns, normalised scores, optional PNG frames.

    ``policy``: ``"selected"`` (the policy the run returned, chosen by offline
    policy selection; the last one for runs without it) or ``"last"``.

    Rebuilds the agent (:func:`load_run_agent`) and rolls ``episodes`` episodes out
    in the real Gymnasium env through the run's decoder. With
    ``frames_dir``, the first episode is rendered (``rgb_array``; headless
    machines need ``MUJOCO_GL=egl`` or ``osmesa``) and saved as PNG frames.
    """
    run = Path(run_dir)
    cfg, env, agent, state, cvae = load_run_agent(run, num_envs=episodes, policy=policy)
    env_id = cfg["env"]["env_id"]
    bound = latent_bound(cfg)
    task, discard = acting_task(cfg, state)
    rets, td = evaluate_policy(env, agent.eval_policy, episodes, max_steps=int(cfg["eval"]["max_steps"]), deterministic=deterministic, seed=seed,
                               return_rollout=True)
    env.close()
    res = {
        "run_dir": str(run),
        "policy": policy if policy == "last" or (run / "selected.pt").is_file() else "last",
        "frames": int(state["frames"]),
        "task": task,
        "episodes": episodes,
        "deterministic": deterministic,
        "return_mean": float(rets.mean()),
        "return_std": float(rets.std()),
        "normalized_d4rl": normalized_score(env_id, float(rets.mean())) if task == "forward" else None,  # D4RL's scale is the forward task's
        "returns": [round(float(r), 2) for r in rets],
    }
    if task_of(env_id).goal_conditioned:  # goals drawn at each reset: the success of each goal's episodes (NaN: none drawn)
        from ..blockstack.goals import success_by_goal

        alive = first_episode_mask(td["next", "done"].reshape(episodes, -1))
        goal = td["desired_goal"][:, 0].argmax(-1)
        per_goal = success_by_goal(td["next", "reward"].reshape(episodes, -1), alive, goal, td["desired_goal"].shape[-1])
        res["success_per_goal"] = per_goal.tolist()
        res["success_rate"] = float(((td["next", "reward"].reshape(episodes, -1) == 0) & alive).any(-1).float().mean())
    if frames_dir is not None:
        res["frames_dir"] = str(render_episode(env_id, cvae, bound, agent, Path(frames_dir), int(cfg["eval"]["max_steps"]), seed, deterministic,
                                                    task=task, discard_decoder=discard))
    return res


def render_episode(env_id, cvae, bound, agent, out: Path, max_steps: int, seed: int, deterministic: bool, task: str = "forward",
                   discard_decoder: bool = False) -> Path:
    import matplotlib.pyplot as plt
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    try:
        env = make_real_env(env_id, cvae, num_envs=1, latent_bound=bound, task=task, discard_decoder=discard_decoder, render_mode="rgb_array")
        agent.attach(env)
        env.set_seed(seed)
        base = env.base_env._env  # the gymnasium vector env
        out.mkdir(parents=True, exist_ok=True)
        frames = [base.render()]
        mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(mode):
            env.rollout(max_steps, agent.eval_policy, callback=lambda *_: frames.append(base.render()))
        for t, frame in enumerate(frames):
            frame = frame[0] if isinstance(frame, (tuple, list)) else frame
            plt.imsave(out / f"frame_{t:04d}.png", frame)
        env.close()
    except Exception as err:  # rendering needs an OpenGL backend
        raise RuntimeError(
            f"rendering {env_id} failed ({type(err).__name__}: {err}); on a headless machine set MUJOCO_GL=egl (GPU) "
            f"or MUJOCO_GL=osmesa (CPU, needs libosmesa) and try again"
        ) from err
    return out
