"""Optimiser and compilation helpers the agents share: fused Adam, CUDA-graph capture, ``torch.compile`` settings."""
from __future__ import annotations

import torch

__all__ = ["COMPILE_MODES", "adam", "compile_setting", "make_capturable"]


def adam(params, lr: float, eps: float = 1e-8, fused: bool = True) -> torch.optim.Adam:
    """Adam; ``fused`` (default) runs one fused kernel over every parameter instead of a Python loop of small ops.

    The same update rule: on the agents' small networks torch's default
    per-tensor Adam costs ~1 ms per step on CPU, the fused one ~0.1 ms
    (``benchmarks/recipe_throughput.py``). ``fused=False`` is torch's default
    implementation (results then match older runs bit for bit).
    """
    params = list(params)
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True) if fused else torch.optim.Adam(params, lr=lr, eps=eps, foreach=False)


COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def compile_setting(value) -> bool | str:
    """An algorithm config's ``compile`` value as :attr:`Agent.compile`: ``False``, or a ``torch.compile`` mode (``True``: ``"default"``)."""
    if value is None or value is False:
        return False
    if value is True:
        return "default"
    if isinstance(value, str) and value in COMPILE_MODES:
        return value
    raise ValueError(f"compile must be true, false or a torch.compile mode ({', '.join(COMPILE_MODES)}), got {value!r}: "
                     "e.g. algo.compile=true, or algo.compile=reduce-overhead for CUDA graphs on a GPU")


def make_capturable(opt: torch.optim.Optimizer) -> None:
    """Let ``opt`` (an Adam) be captured in a CUDA graph: ``capturable`` groups, step counts on the parameters' device."""
    for group in opt.param_groups:
        group["capturable"] = True
        for p in group["params"]:
            state = opt.state.get(p, {})
            if torch.is_tensor(state.get("step")) and state["step"].device != p.device:
                state["step"] = state["step"].to(p.device, torch.float32)
