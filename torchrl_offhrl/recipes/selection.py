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

Why ``last`` by default. The model's verdict on a policy is only as long as
its episodes. With the demo's 100-step episodes branched from any dataset
state the model return is capped by the horizon, and every criterion
preferred the policy closest to the data, a near-behaviour-cloning one (real
score 29-33), over the running ones (64-93) the same runs reached, with 250
model episodes per policy as with 50 (``docs/results/demo_robustness_notes.md``,
``scripts/diagnostics/selection_probe.py``); :func:`horizon_warning` now
says so for any run that combines a model criterion with model episodes
shorter than the real ones. With the paper's 1,000-step episodes from the
data's start states (the full scale), ``model_lcb`` picked a policy above
the untrained start and the data in 6 of 6 hopper-medium tuning runs (the
last policy: 4 of 6), then in 2 of 5 evaluation runs (the last policy: 3 of
5; ``docs/results/full/experiments.md``): the worst member's return falls as
soon as a policy leaves the data, so early, near-data policies often win.
``torchrl_offhrl/results/robustness.py`` and the tuning pages of
``torchrl_offhrl/results/table1.py`` score every criterion on every run they make.

Evaluations at step 0 (the untrained agent) are candidates only with
``include_start=True``: by default the returned policy is a trained one.
"""
from __future__ import annotations

import copy

__all__ = ["CRITERIA", "PolicySelector", "horizon_warning"]

#: criterion -> the evaluation-record key it maximises (None: the last evaluation wins)
CRITERIA: dict[str, str | None] = {
    "model_lcb": "model_discounted_min_member", "model_mean": "model_discounted_mean",
    "model_lcb_undiscounted": "model_return_min_member", "model_mean_undiscounted": "model_return_mean", "last": None,
}


def horizon_warning(criterion: str, horizon: int | None, episode_steps: int) -> str | None:
    """Why a model criterion may mislead with this model env (None if it should not): its episodes (``horizon``, the
    model env's and so the evaluation's) stop before the real env's ``episode_steps``.

    >>> horizon_warning("model_lcb", 100, 1000)[:44]
    'selection.criterion=model_lcb reads 100-step'
    >>> horizon_warning("last", 100, 1000) is None, horizon_warning("model_lcb", 1000, 1000) is None
    (True, True)
    """
    if CRITERIA.get(criterion) is None or horizon is None or horizon >= episode_steps:
        return None
    return (f"selection.criterion={criterion} reads {horizon}-step model episodes (model_env.horizon) where a real episode runs "
            f"{episode_steps} steps: the model return is capped by the horizon and cannot tell a gait that runs past the data "
            "from one that falls (on the demo's tuning seeds every model criterion then picked near-behaviour-cloning policies); "
            "selection.criterion=last returns the last policy, as configs/demo.yaml does")


class PolicySelector:
    """Keeps the agent state of the best evaluation by an offline criterion.

    Args:
        criterion: a key of :data:`CRITERIA`.
        include_start: whether the evaluation at step 0 is a candidate.

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

    def __init__(self, criterion: str = "last", include_start: bool = False):
        if criterion not in CRITERIA:
            raise ValueError(f"selection.criterion must be one of {sorted(CRITERIA)}, got {criterion!r}")
        self.criterion, self.key, self.include_start = criterion, CRITERIA[criterion], bool(include_start)
        self.selected: dict | None = None
        self._count = 0

    def score(self, record: dict) -> float | None:
        """The record's offline score (None: the record lacks it, e.g. an agent evaluated without a model env)."""
        if self.key is None:
            return float(self._count)  # later is better: the last evaluation wins
        v = record.get(self.key)
        return None if v is None else float(v)

    def consider(self, record: dict, agent, step: int) -> bool:
        """Take the evaluation ``record`` of ``agent`` at ``step`` into account; True when it becomes the selected one."""
        index = self._count
        self._count += 1
        if step == 0 and not self.include_start:
            return False
        s = self.score(record)
        if s is None:
            if self.key is not None and self.selected is None and step > 0:
                raise ValueError(f"selection.criterion={self.criterion} reads {self.key!r}, which the evaluation records of this run "
                                 "lack (it needs the model env's evaluation: eval.model_env=true on a model-env agent); "
                                 "use selection.criterion=last")
            return False
        if self.selected is not None and s <= self.selected["score"]:
            return False
        # the last policy is the run's own checkpoint: no copy kept
        state = None if self.key is None else copy.deepcopy(agent.state_dict())
        self.selected = {"index": index, "step": int(step), "score": s, "agent": state}
        return True

    def state_dict(self) -> dict:
        return {"criterion": self.criterion, "include_start": self.include_start, "count": self._count, "selected": self.selected}

    def load_state_dict(self, state: dict | None) -> None:
        if not state:
            return
        if state.get("criterion") != self.criterion:
            raise ValueError(f"the checkpoint selected its policy by {state.get('criterion')!r}, this run by {self.criterion!r}: "
                             "resume with the same selection.criterion")
        self._count, self.selected = int(state["count"]), state["selected"]
