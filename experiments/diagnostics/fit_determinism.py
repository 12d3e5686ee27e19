"""Is a model fit a function of its data and seed alone? The same CVAE fit repeated, and at another thread count.

    python experiments/diagnostics/fit_determinism.py DATASET.hdf5 [--steps 300] [--threads 2 1]

Fits the demo's CVAE (MLP(256, 256), lr 1e-3, batch 256) for ``--steps`` steps on the same data with the same seed,
twice at the first thread count and once at each other one, and prints the largest weight difference of each fit
from the first. A nonzero difference between the two
fits at one thread count means the fit is not reproducible even on one machine; one only across thread counts means
the machine's thread count is part of the result (issue 37: the demo's untrained start, which is the decoder's mean
action, differed between two machines on bit-identical datasets).
"""
import argparse

import torch

from torchrl_offhrl.data import load_dataset
from torchrl_offhrl.models import ConditionalVAE


def fit(data, steps: int, threads: int, seed: int = 0) -> ConditionalVAE:
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=[256, 256], kl_weight=0.05)
    cvae.fit(data, val_ratio=0.1, split_seed=seed, progress=False, seed=seed, lr=1e-3, batch_size=256, max_epochs=200, max_steps=steps, patience=5)
    return cvae


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    a = p.parse_args()
    data = load_dataset(a.dataset)
    runs = [(a.threads[0], fit(data, a.steps, a.threads[0]))]
    runs += [(t, fit(data, a.steps, t)) for t in [a.threads[0], *a.threads[1:]]]
    ref_w = torch.cat([q.detach().flatten() for q in runs[0][1].parameters()])
    for i, (t, m) in enumerate(runs):
        w = torch.cat([q.detach().flatten() for q in m.parameters()])
        print(f"fit {i} ({t} thread{'s' * (t != 1)}): max |weight - fit 0| = {(w - ref_w).abs().max().item():.3e}")


if __name__ == "__main__":
    main()
