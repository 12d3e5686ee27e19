"""Why ``algo.compile=true`` does not pay on this CPU: inductor's kernels that write one-byte tensors (issue 75).

    python benchmarks/compile_cpu.py [--threads 1] [--repeats 500]

A compiled training step saves, for each ReLU's backward, the mask ``y <= 0`` as a ``bool`` tensor (the partitioner's
choice: a quarter of a float's memory). This script times, eager and through ``torch.compile`` (inductor, the
default backend), the pointwise kernel of one hidden layer of our twin critics (``relu(x + b)`` on ``[2, 256, 256]``:
two members, batch 256, width 256) with each kind of second output: none, the mask as ``bool``, as ``uint8``, as
``float32``, and the mask alone. Where a kernel that writes one-byte elements runs many times slower compiled than
eager, a compiled update spends its time there (``benchmarks/README.md``: the update's profile), whatever the Python
overhead it removes. The ratio column is eager time / compiled time (> 1: compiling pays).
"""
from __future__ import annotations

import argparse
import time

import torch


def relu_only(x, b):
    return torch.relu(x + b)


def relu_mask_bool(x, b):
    y = torch.relu(x + b)
    return y, y <= 0


def relu_mask_uint8(x, b):
    y = torch.relu(x + b)
    return y, (y <= 0).to(torch.uint8)


def relu_mask_float(x, b):
    y = torch.relu(x + b)
    return y, (y <= 0).float()


def mask_alone(x, b):
    return x + b <= 0


KERNELS = (relu_only, relu_mask_bool, relu_mask_uint8, relu_mask_float, mask_alone)


def time_us(fn, args, repeats: int) -> float:
    for _ in range(20):
        fn(*args)
    t = time.perf_counter()
    for _ in range(repeats):
        fn(*args)
    return (time.perf_counter() - t) / repeats * 1e6


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        import platform

        return platform.processor() or "unknown CPU"


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=500)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    from torch._inductor.cpu_vec_isa import pick_vec_isa

    torch.manual_seed(0)
    args = (torch.randn(2, 256, 256), torch.randn(2, 1, 256))
    print(f"{cpu_name()}; torch {torch.__version__}, {torch.get_num_threads()} thread(s), ATen CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}, inductor vector ISA {pick_vec_isa()}\n")
    print("| kernel on [2, 256, 256] | eager us | compiled us | eager / compiled |")
    print("|---|---|---|---|")
    for fn in KERNELS:
        eager = time_us(fn, args, a.repeats)
        compiled = time_us(torch.compile(fn), args, a.repeats)
        print(f"| {fn.__name__} | {eager:.0f} | {compiled:.0f} | {eager / compiled:.2f} |", flush=True)


if __name__ == "__main__":
    main()
