"""The FLOPs of what a ``torch.profiler`` run computed: its leaf matrix products only (shared by the benchmarks).

The profiler's ``flops`` are set per recorded op from that op's own input shapes, and one computation can be recorded
at several levels: under ``torch.vmap`` (TorchRL's twin critics, a seeds' batch) a linear layer is recorded as the
logical per-member ``aten::addmm``, inside it an ``aten::mm``, and inside that the ``aten::bmm`` over every member that
does the work, so summing every event's ``flops`` (``prof.key_averages()``) counts a vmapped layer 2x (two members:
addmm + mm are one member each, bmm both). Only an event with FLOPs none of whose descendants has any is counted here.

    >>> import torch
    >>> from torch.profiler import profile
    >>> w, x = torch.randn(2, 8, 4), torch.randn(5, 4)
    >>> with profile(with_flops=True) as prof:
    ...     _ = torch.vmap(lambda wi: x @ wi.T)(w)
    >>> leaf_flops(prof) == 2 * 2 * 5 * 4 * 8   # one [2, 5, 4] x [2, 4, 8] product, 2 FLOPs per multiply-add
    True
"""
from __future__ import annotations

__all__ = ["leaf_flops"]


def leaf_flops(prof) -> float:
    """The FLOPs of ``prof``'s events that computed them themselves (no descendant with FLOPs of its own)."""

    def has_flops_below(event) -> bool:
        return any(c.flops or has_flops_below(c) for c in event.cpu_children)

    return float(sum(e.flops for e in prof.events() if e.flops and not has_flops_below(e)))
