"""Offline policy selection: which of a run's policies to return, chosen without the real env.

Training on a learned model swings: a policy can be good at one evaluation
and lose its gait at the next (``docs/results/demo_robustness.md``). The
last update's policy is then a draw from those swings. A
:class:`PolicySelector` looks at every evaluation of a run and keeps the
agent's state at the one with the best *offline* score: a number computed
from the pessimistic model env, never from the real env (the real-env
evaluation stays in the record for reporting, unread by the selector).

Criteria (``selection.criterion``):

* ``last`` (default): no selection; the last policy.
* ``model_lcb``: the best *discounted* model return (the agent's own
  objective, its ``gamma``) of the worst ensemble member
  (``model_discounted_min_member``: every member rolls the policy out from
  the same start states, see
  :meth:`~torchrl_offhrl.recipes.evaluation.Evaluator.model_metrics`). A
  lower confidence bound over the ensemble: a policy that scores high only
  under some members is exploiting their errors.
* ``model_mean``: the best discounted mean model return.
* ``model_lcb_undiscounted`` / ``model_mean_undiscounted``: the same on the
  undiscounted return.

Why the model episodes are whole-length. The model's verdict on a policy
is only as long as its episodes: with the demo's 100-step episodes branched
from any dataset state the model return is capped by the horizon, and every
criterion preferred the policy closest to the data over the running ones the
same runs reached, however many model episodes it was given
(``docs/results/demo_robustness_notes.md``,
``experiments/diagnostics/selection_probe.py``). Evaluations therefore roll
their model episodes for a whole real-episode length (``eval.max_steps``)
from the data's start states, whatever the training horizon. Even then the
worst member's return falls as soon as a policy leaves the data, so early,
near-data policies often win (``docs/results/full/experiments.md``).
``experiments/results/robustness.py`` and the tuning pages of
``experiments/results/table1.py`` score every criterion on every run they make.

Evaluations at step 0 (the untrained agent) are candidates only with
``include_start=True``: by default the returned policy is a trained one.

``model_gain_lcb`` and the guard. Both compare a policy with the policy the
run *started from* (the evaluation at step 0: with the default
``model_env.latent_origin=best`` the decoder at the latent of the data's
highest-return episodes at each state, a behaviour cloner of them) on the same model episodes: every
evaluation rolls its policy out from the same data start states under the
same member per episode (``member_draw="cyclic"``) for a whole real-episode
length, so the two policies' returns pair up episode by episode.
:func:`paired_gain_lcb` is the smallest, over the ensemble members, of the
one-sided 95% lower bound of the mean paired gain under that member. The
criterion ``model_gain_lcb`` returns the evaluation where it is largest; the
**guard** (``selection.guard``, on by default) then returns the start policy
instead whenever the chosen policy's bound is not above 0: no member of the
ensemble shows with confidence that the trained policy does better than
where it started, so the run hands back its start rather than a policy that
may be worse. The summary says whether the guard fired. Why the worst
member's bound on whole-length returns: pooled over the members it passes
policies the real env scores well below their start, truncated returns trade
one dataset's certified gains for another's, and no comparison of the model's
episodes tried tells most better gaits from worse ones
(``docs/results/offline_probes.md``).

The return cap (``selection.return_cap: data``, the default). Before pairing,
every model episode's return, the start's and the policy's, is clipped at
:func:`data_return_cap`: the best return of a complete episode in the data.
A model that pays a policy more than any episode of the data ever earned is
extrapolating, and a gain measured there is not evidence: on halfcheetah the
model pays the start itself above the data's best, and the guard without the
cap passed policies the model paid a few percent more while the real env
scored them far below their start (the cheetah stops; the members agree on
the exploit; the numbers are in ``docs/results/offline_probes.md``). With the cap a gain counts
only where it lifts episodes the start leaves below the data's best (an episode
the pessimism ended early, a fall): on the design runs it removed every wrong
pass and the small right ones of halfcheetah-medium, and on the held-out runs
it decided as the uncapped guard (``docs/results/offline_probes.md``; it was
looked for after evaluation-seed runs showed the wrong passes, and says so
there). ``return_cap: none`` compares the returns as they are.

The percentile BC (``selection.fallback``, :mod:`~torchrl_offhrl.recipes.fallback`).
The start is one cloner of the data's best episodes; a plain regression of
the same episodes' actions is another, evaluated at the run's end on the
start's own model episodes. With ``bc_unless_start`` (the default) the
trained policy must show a gain over both, and a fired guard returns the BC
unless the start shows a gain over it: the model rarely tells the two
apart, and on the design data the BC returned more than the start on average
(``docs/results/offline_probes.md``, section 4, has the runs, rule and scores).
``start_unless_bc`` returns the start unless the BC shows a gain over it;
``start`` fits no BC.
"""
from __future__ import annotations

import copy
import math

__all__ = ["CRITERIA", "GAIN_Z", "PolicySelector", "data_return_cap", "paired_gain_lcb"]

#: one-sided 95% normal quantile of :func:`paired_gain_lcb`
GAIN_Z = 1.645

#: criterion -> the evaluation-record key it maximises (None: the last evaluation wins)
CRITERIA: dict[str, str | None] = {
    "model_lcb": "model_discounted_min_member", "model_mean": "model_discounted_mean",
    "model_lcb_undiscounted": "model_return_min_member", "model_mean_undiscounted": "model_return_mean", "last": None,
    "model_gain_lcb": "model_episode_returns",  # paired with the start policy's episodes: paired_gain_lcb
}


def data_return_cap(data, max_steps: int | None = None) -> float | None:
    """The highest return the data vouches for in a model episode of ``max_steps`` steps: the guard's return cap.

    The best undiscounted return of a complete episode in ``data`` (an
    :class:`~torchrl_offhrl.data.OfflineDataset`; every episode when none is
    marked complete). When the model episodes are longer than every episode
    of the data (``max_steps`` above the longest), the best return per step
    of a data episode times ``max_steps`` if that is higher: the data cannot
    show what a longer episode earns, and the cap must not end a policy's
    gain where the data merely stopped recording. None for data without
    episodes.

    >>> from torchrl_offhrl.data import make_toy_dataset
    >>> ds = make_toy_dataset(num_episodes=3, episode_length=5)
    >>> data_return_cap(ds, max_steps=5) == float(ds.episode_returns().max())
    True
    """
    returns, lengths = data.episode_returns(complete_only=True), data.episode_lengths(complete_only=True)
    if returns.numel() == 0:
        returns, lengths = data.episode_returns(), data.episode_lengths()
    if returns.numel() == 0:
        return None
    cap = float(returns.max())
    if max_steps is not None and int(max_steps) > int(lengths.max()):
        cap = max(cap, float((returns / lengths.clamp(min=1)).max()) * int(max_steps))
    return cap


def paired_gain_lcb(record: dict, start: dict, z: float = GAIN_Z, cap: float | None = None) -> float | None:
    """The worst member's lower confidence bound on a policy's gain over the start policy, on paired model episodes.

    ``record`` and ``start`` are evaluation records holding
    ``model_episode_returns`` and ``model_episode_members`` (one value per
    model episode; episode ``i`` starts from the same state under the same
    member in both). Per member ``k``: the mean of the paired differences
    ``d_i = R_i - R_start_i`` over its episodes minus ``z`` standard errors
    (a member with one episode: its difference); the smallest over members.
    With ``cap`` (:func:`data_return_cap`) every return is first clipped at
    it: ``d_i = min(R_i, cap) - min(R_start_i, cap)``, so a gain the model
    pays above the data's best return counts as none.
    None when either record lacks the episodes or they do not pair up.

    >>> start = {"model_episode_returns": [10.0, 10.0, 20.0, 20.0], "model_episode_members": [0, 1, 0, 1]}
    >>> better = {"model_episode_returns": [12.0, 11.0, 22.0, 21.0], "model_episode_members": [0, 1, 0, 1]}
    >>> paired_gain_lcb(better, start, z=0.0)   # member 0 gains 2, member 1 gains 1: the worst member
    1.0
    >>> paired_gain_lcb(better, start) < 1.0     # minus 1.645 standard errors (here 0: every gain equal)
    False
    >>> paired_gain_lcb({"model_episode_returns": [12.0, 8.0, 22.0, 21.0], "model_episode_members": [0, 1, 0, 1]}, start, z=0.0)
    -0.5
    >>> paired_gain_lcb(better, start, z=0.0, cap=15.0)   # the 20s and 21-22s clip to 15: only the first episodes' gains count
    0.5
    """
    r, s = record.get("model_episode_returns"), start.get("model_episode_returns")
    m, ms = record.get("model_episode_members"), start.get("model_episode_members")
    if r is None or s is None or m is None or len(r) != len(s) or list(m) != list(ms or []):
        return None
    clip = (lambda x: min(float(x), float(cap))) if cap is not None else float
    by_member: dict = {}
    for ri, si, k in zip(r, s, m):
        by_member.setdefault(k, []).append(clip(ri) - clip(si))
    bounds = []
    for d in by_member.values():
        mean = sum(d) / len(d)
        if len(d) > 1:
            var = sum((x - mean) ** 2 for x in d) / (len(d) - 1)
            mean -= z * math.sqrt(var / len(d))
        bounds.append(mean)
    return min(bounds) if bounds else None


def _episodes(record: dict) -> dict:
    """The part of an evaluation record :func:`paired_gain_lcb` pairs: every model episode's return and member."""
    return {k: record.get(k) for k in ("model_episode_returns", "model_episode_members")}


class PolicySelector:
    """Keeps the agent state of the best evaluation by an offline criterion, and guards the return against the start.

    Args:
        criterion: a key of :data:`CRITERIA`.
        include_start: whether the evaluation at step 0 is a candidate.
        guard: keep the start policy (step 0) and return it instead of the
            selected one when :func:`paired_gain_lcb` of the selected
            evaluation against the start is not above 0 (:meth:`verdict`).
        return_cap: the guard's (and ``model_gain_lcb``'s) cap on every model
            episode's return (:func:`data_return_cap`; None: no cap).
        prefer: which fallback a fired guard keeps when neither the start
            nor a percentile BC shows a gain over the other (``"bc"`` or
            ``"start"``; :meth:`verdict`).

    ``consider(record, agent, step)`` after each evaluation; ``selected``
    is ``{"index", "step", "score", "agent"}`` of the best so far (None
    before the first candidate; ``agent`` is None for ``last``: the run's
    checkpoint holds that policy). Ties keep the earlier policy. The state
    is part of the run's checkpoint (:meth:`state_dict`), so a resumed run
    selects as an uninterrupted one.

    Examples:
        >>> class Agent:
        ...     def __init__(self): self.w = 0
        ...     def state_dict(self): return {"w": self.w}
        >>> sel, agent = PolicySelector("model_lcb"), Agent()
        >>> for i, (w, lcb) in enumerate([(0, 900.0), (1, 500.0), (2, 700.0), (3, 650.0)]):
        ...     agent.w = w
        ...     _ = sel.consider({"model_discounted_min_member": lcb}, agent, step=i * 100)
        >>> sel.selected["step"], sel.selected["agent"]
        (200, {'w': 2})
    """

    def __init__(self, criterion: str = "last", include_start: bool = False, guard: bool = False, return_cap: float | None = None,
                 prefer: str = "bc"):
        if criterion not in CRITERIA:
            raise ValueError(f"selection.criterion must be one of {sorted(CRITERIA)}, got {criterion!r}")
        self.criterion, self.key, self.include_start = criterion, CRITERIA[criterion], bool(include_start)
        self.guard = bool(guard)
        self.return_cap = None if return_cap is None else float(return_cap)
        if prefer not in ("bc", "start"):
            raise ValueError(f"prefer must be 'bc' or 'start', got {prefer!r}")
        self.prefer = prefer
        self.selected: dict | None = None
        self.start: dict | None = None  # the step-0 evaluation: its record's model episodes and (guard) its agent state
        self._count = 0

    @property
    def paired(self) -> bool:
        """Whether the criterion or the guard compares policies with the start's model episodes."""
        return self.guard or self.criterion == "model_gain_lcb"

    def score(self, record: dict) -> float | None:
        """The record's offline score (None: the record lacks it, e.g. an agent evaluated without a model env)."""
        if self.key is None:
            return float(self._count)  # later is better: the last evaluation wins
        if self.criterion == "model_gain_lcb":
            return None if self.start is None else paired_gain_lcb(record, self.start["record"], cap=self.return_cap)
        v = record.get(self.key)
        return None if v is None else float(v)

    def consider(self, record: dict, agent, step: int) -> bool:
        """Take the evaluation ``record`` of ``agent`` at ``step`` into account; True when it becomes the selected one."""
        index = self._count
        self._count += 1
        if step == 0 and self.paired and self.start is None:
            self.start = {"index": index, "record": _episodes(record), "agent": copy.deepcopy(agent.state_dict()) if self.guard else None}
        if step == 0 and not self.include_start:
            return False
        s = self.score(record)
        if s is None:
            if self.key is not None and self.selected is None and step > 0:
                why = ("the evaluation at step 0 (eval.at_start=true) and " if self.criterion == "model_gain_lcb" and self.start is None else "")
                raise ValueError(f"selection.criterion={self.criterion} reads {self.key!r}, which the evaluation records of this run "
                                 f"lack (it needs {why}the model env's evaluation: eval.model_env=true on a model-env agent); "
                                 "use selection.criterion=last")
            return False
        if self.selected is not None and s <= self.selected["score"]:
            return False
        # the last policy is the run's own checkpoint: no copy kept
        state = None if self.key is None else copy.deepcopy(agent.state_dict())
        self.selected = {"index": index, "step": int(step), "score": s, "agent": state}
        if self.guard:  # what the guard pairs with the start's episodes
            self.selected["episodes"] = _episodes(record)
        return True

    def verdict(self, fallback: dict | None = None) -> dict | None:
        """The guard's decision on the selected policy (None without a guard): ``{"fired", "gain_lcb", "against", "reason", ...}``.

        Without ``fallback`` the selected policy must show a gain over the
        start (``gain_lcb``: the worst member's bound, :func:`paired_gain_lcb`),
        else the start is returned. ``fallback`` is the evaluation record of
        a percentile BC of the same episodes (:mod:`~torchrl_offhrl.recipes.fallback`;
        its model episodes pair up with the start's): the selected policy must
        then show a gain over both (``gain_lcb`` the smaller bound), and a
        fired guard returns one of them (``against``): with the selector's
        ``prefer="bc"`` the BC unless the start shows a gain over it, with ``prefer="start"``
        the start unless the BC shows a gain over it
        (``start_over_bc_lcb`` / ``bc_over_start_lcb``). A BC whose episodes
        do not pair up is left out (the reason says so).
        """
        if not self.guard:
            return None
        if self.start is None or self.start.get("agent") is None:
            return {"fired": False, "gain_lcb": None, "reason": "no evaluation at step 0 (eval.at_start=false): nothing to compare with; "
                                                                 "the selected policy is returned unguarded"}
        prefer = self.prefer
        cap, start = self.return_cap, self.start["record"]
        bc = None if fallback is None else _episodes(fallback)
        start_over_bc = None if bc is None else paired_gain_lcb(start, bc, cap=cap)
        bc_over_start = None if bc is None else paired_gain_lcb(bc, start, cap=cap)
        if start_over_bc is None:
            bc, against = None, "start"
        elif prefer == "bc":
            against = "start" if start_over_bc > 0 else "bc"
        else:
            against = "bc" if bc_over_start > 0 else "start"
        name = {"start": "the start policy", "bc": "the percentile BC"}[against]
        why = ("" if fallback is None else
               "; the percentile BC's model episodes do not pair with the start's, it is left out" if bc is None else
               {("bc", "bc"): "; the start shows no gain over the percentile BC, the fallback (selection.fallback=bc_unless_start)",
                ("bc", "start"): "; the start shows a gain over the percentile BC and stays the fallback",
                ("start", "start"): "; the percentile BC shows no gain over the start, the fallback (selection.fallback=start_unless_bc)",
                ("start", "bc"): "; the percentile BC shows a gain over the start and is the fallback"}[(prefer, against)])
        out = {"against": against, "return_cap": cap,
               "start_over_bc_lcb": None if start_over_bc is None else float(start_over_bc),
               "bc_over_start_lcb": None if bc_over_start is None else float(bc_over_start)}
        if self.selected is None:
            return {"fired": True, "gain_lcb": None, **out, "reason": f"no trained policy was evaluated: {name} is returned{why}"}
        over_start = paired_gain_lcb(self.selected["episodes"], start, cap=cap)
        over_bc = None if bc is None else paired_gain_lcb(self.selected["episodes"], bc, cap=cap)
        out.update({"gain_lcb_over_start": over_start, "gain_lcb_over_bc": over_bc})
        if over_start is None:
            return {"fired": True, "gain_lcb": None, **out,
                    "reason": f"the evaluations lack paired model episodes (eval.model_env=false?): {name} is returned"}
        lcb = over_start if over_bc is None else min(over_start, over_bc)
        fired = not lcb > 0
        over = "the start policy" if bc is None else "the start policy and the percentile BC"
        capped = "" if cap is None else f", returns clipped at the data's best episode, {cap:.4g}"
        reason = (f"no ensemble member shows a gain over {over} with 95% confidence (worst member's bound {lcb:.4g}{capped}): "
                  f"{name} is returned{why}" if fired else
                  f"every ensemble member shows a gain over {over} (worst member's 95% lower bound {lcb:.4g}{capped}){why if bc is None else ''}")
        return {"fired": fired, "gain_lcb": float(lcb), **out, "reason": reason}

    def state_dict(self) -> dict:
        return {"criterion": self.criterion, "include_start": self.include_start, "count": self._count, "selected": self.selected,
                "guard": self.guard, "start": self.start}

    def load_state_dict(self, state: dict | None) -> None:
        if not state:
            return
        if state.get("criterion") != self.criterion:
            raise ValueError(f"the checkpoint selected its policy by {state.get('criterion')!r}, this run by {self.criterion!r}: "
                             "resume with the same selection.criterion")
        self._count, self.selected = int(state["count"]), state["selected"]
        self.start = state.get("start")
