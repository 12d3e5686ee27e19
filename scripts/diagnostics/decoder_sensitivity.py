"""Does the CVAE decoder use its latent? The spread of its actions over latents, next to the data's action spread.

    python scripts/diagnostics/decoder_sensitivity.py [hydra overrides of configs/demo.yaml ...]
    python scripts/diagnostics/decoder_sensitivity.py cvae.kl_weight=0.05
    python scripts/diagnostics/decoder_sensitivity.py --config=offline_train   # full scale (first argument)

For 2,000 dataset states, decodes 16 latents drawn from the prior and 16
corners of the latent box (+-2, the policies' range) and prints the standard
deviation of the decoded actions over latents (mean over states), per action
dimension, next to the data's action standard deviation. A decoder whose
spread is a few percent of the data's has collapsed onto its mean action (the
KL term won): a latent policy then cannot act differently from behaviour
cloning, whatever it learns.
"""
from __future__ import annotations

import sys

import torch

from torchrl_offhrl.recipes.config import compose, model_config, resolve_dataset
from torchrl_offhrl.recipes.pipeline import fit_or_load_models
from torchrl_offhrl.utils import to_plain


def main(overrides: list[str]) -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    name = "demo"
    if overrides and overrides[0].startswith("--config="):  # e.g. --config=offline_train: the full-scale settings
        name, overrides = overrides[0].split("=", 1)[1], overrides[1:]
    cfg = to_plain(compose(name, overrides))
    data = resolve_dataset(cfg)
    _, cvae, info = fit_or_load_models(model_config(cfg), data, progress=False)
    obs, act = data["observation"][:2000], data["action"][:2000]
    zs = torch.randn(16, obs.shape[0], cvae.latent_dim)
    bound = float(cfg["model_env"]["latent_bound"])
    with torch.no_grad():
        prior = torch.stack([cvae.decoder(obs, z) for z in zs]).std(0).mean(0)
        corners = torch.stack([cvae.decoder(obs, bound * torch.sign(z)) for z in zs]).std(0).mean(0)
    print(f"models {info['model_dir']}, kl_weight {cfg['cvae']['kl_weight']}, latent dim {cvae.latent_dim}")
    print(f"data action std per dim          {act.std(0).numpy().round(3)}")
    print(f"decoder std over z ~ N(0, I)     {prior.numpy().round(3)}  ({(prior / act.std(0)).mean():.0%} of the data's)")
    print(f"decoder std over z = +-{bound:g} corners {corners.numpy().round(3)}  ({(corners / act.std(0)).mean():.0%} of the data's)")


if __name__ == "__main__":
    main(sys.argv[1:])
