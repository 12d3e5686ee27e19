"""Does the CVAE decoder use its latent? The spread of its actions over latents, next to the data's action spread.

    python experiments/diagnostics/decoder_sensitivity.py [hydra overrides of configs/demo.yaml ...]
    python experiments/diagnostics/decoder_sensitivity.py cvae.kl_weight=0.05
    python experiments/diagnostics/decoder_sensitivity.py --config=offline_train   # full scale (first argument)

Prints :func:`torchrl_offhrl.models.decoder_sensitivity` for the config's (cached) CVAE on its held-out episodes, per
action dimension: the decoded actions' std over 16 corners of the latent box and over 16 prior draws, next to the data's
action std. A run's calibration report prints the shares; this shows them per dimension for a config without training.
A decoder whose spread is a few percent of the data's has collapsed onto its mean action (the KL term won): a latent
policy then cannot act differently from behaviour cloning, whatever it learns.
"""
from __future__ import annotations

import sys

import torch

from torchrl_offhrl.envs.rules import latent_bound_rule
from torchrl_offhrl.models import decoder_sensitivity
from torchrl_offhrl.recipes.config import compose, model_config, resolve_dataset
from torchrl_offhrl.recipes.pipeline import fit_or_load_models
from torchrl_offhrl.utils import to_plain


def main(overrides: list[str]) -> None:
    torch.set_num_threads(1)
    name = "demo"
    if overrides and overrides[0].startswith("--config="):  # e.g. --config=offline_train: the full-scale settings
        name, overrides = overrides[0].split("=", 1)[1], overrides[1:]
    cfg = to_plain(compose(name, overrides))
    data = resolve_dataset(cfg)
    mcfg = model_config(cfg)
    _, cvae, info = fit_or_load_models(mcfg, data, progress=False)
    held_out = data.split(mcfg["dataset"].get("val_ratio", 0.1), seed=mcfg["seed"])[1]
    bound = cfg["model_env"]["latent_bound"]
    bound = latent_bound_rule(cvae, held_out)[0] if bound == "auto" else float(bound)
    s = decoder_sensitivity(cvae, held_out, bound)
    fmt = lambda xs: "[" + ", ".join(f"{x:.3f}" for x in xs) + "]"  # noqa: E731
    print(f"models {info['model_dir']}, kl_weight {cfg['cvae']['kl_weight']}, latent dim {cvae.latent_dim}, box +-{bound:.3g}")
    print(f"data action std per dim             {fmt(s['data_std'])}")
    print(f"decoder std over z ~ N(0, I)        {fmt(s['prior_std'])}  ({s['prior_share']:.0%} of the data's)")
    print(f"decoder std over the box's corners  {fmt(s['corner_std'])}  ({s['corner_share']:.0%} of the data's)")


if __name__ == "__main__":
    main(sys.argv[1:])
