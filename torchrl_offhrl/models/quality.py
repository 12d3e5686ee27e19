"""How good the fitted models are, from data they never trained on: numbers a user reads before trusting a model env.

* :func:`ensemble_quality`: are the members wrong together (bias) or apart
  (disagreement)? The ensemble mean's one-step error on held-out transitions
  next to the members' spread, in the units of the data's state change.
* :func:`decoder_sensitivity`: does the CVAE's decoder use its latent? How far
  its action moves over the latent box, next to the data's action spread.

Both are part of a run's calibration report
(:func:`~torchrl_offhrl.envs.offline_rules`), computed on the held-out
episodes of the models' own split.
"""
from __future__ import annotations

import torch

__all__ = ["decoder_sensitivity", "ensemble_quality"]


@torch.no_grad()
def ensemble_quality(ensemble, data, chunk: int = 65536) -> dict:
    """One-step quality of ``ensemble`` on the transitions of ``data`` (an :class:`~torchrl_offhrl.data.OfflineDataset`).

    Reasoning. The P-MDP trusts a state-action pair while the members agree, so
    the members' disagreement has to be about as large as their error there:
    an ensemble whose mean is wrong by much more than its members' spread
    (``error_over_spread`` well above 1) is confidently wrong, and the
    pessimism cannot see it. Measured on held-out episodes, the error is the
    one an agent meets on data-like pairs; off the data it only grows.

    Returns a dict of floats:

    * ``state_error``: mean over pairs and state dimensions of ``|mean_k(s'_k) - s'| / std(s' - s)``
      (the data's state-change std: 1.0 is an error as large as a typical step);
    * ``state_spread``: the same mean of the members' standard deviation of ``s'_k``, in the same units;
    * ``error_over_spread``: their ratio;
    * ``reward_error`` and ``reward_spread``: the reward's mean absolute error and member std, in the reward's units
      (None for an ensemble without a reward model);
    * ``pairs``: how many transitions were read.

    Example:
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import DynamicsEnsemble
        >>> data = make_toy_dataset(num_episodes=10, episode_length=20)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(16,))
        >>> sorted(ensemble_quality(ens, data))
        ['error_over_spread', 'pairs', 'reward_error', 'reward_spread', 'state_error', 'state_spread']
    """
    device = next(ensemble.parameters()).device
    td = data.data
    obs, act, nxt = td.get("observation"), td.get("action"), td.get(("next", "observation"))
    rew = td.get(("next", "reward")).reshape(-1)
    n = obs.shape[0]
    if n == 0:
        raise ValueError("ensemble_quality: no transitions to measure on")
    scale = ensemble.delta_std.reshape(-1)
    sums = torch.zeros(4, dtype=torch.float64)
    has_reward = True
    for s in range(0, n, chunk):
        o, a = obs[s : s + chunk].to(device), act[s : s + chunk].to(device)
        out = ensemble.predict(o, a)
        pred = out["next_observation"] / scale  # [K, B, D] in the state change's std units
        sums[0] += (pred.mean(0) - nxt[s : s + chunk].to(device) / scale).abs().mean(-1).double().sum().cpu()
        sums[1] += pred.std(0, unbiased=False).mean(-1).double().sum().cpu()
        r = out.get("reward")
        if r is None:
            has_reward = False
            continue
        sums[2] += (r.mean(0) - rew[s : s + chunk].to(device)).abs().double().sum().cpu()
        sums[3] += r.std(0, unbiased=False).double().sum().cpu()
    mean = (sums / n).tolist()
    return {"state_error": mean[0], "state_spread": mean[1], "error_over_spread": mean[0] / max(mean[1], 1e-12),
            "reward_error": mean[2] if has_reward else None, "reward_spread": mean[3] if has_reward else None, "pairs": n}


@torch.no_grad()
def decoder_sensitivity(cvae, data, bound: float, num_latents: int = 16, num_states: int = 2000, seed: int = 0) -> dict:
    """How far ``cvae``'s decoder moves its action when only the latent changes, next to the data's action spread.

    Reasoning. A latent policy acts only through the decoder: if the decoded
    action barely changes over the latent box (the KL term won and the
    posterior collapsed), no policy can act differently from the decoder's
    mean action, whatever it learns, and every agent's curve stays flat. For
    ``num_states`` states of ``data`` (evenly spaced), ``num_latents`` latents
    are decoded at random corners of the box ``[-bound, bound]`` (where a
    policy's extreme actions land) and drawn from the prior ``N(0, I)``; the
    standard deviation of the decoded actions over those latents, averaged
    over states, is compared with the standard deviation of the data's actions.

    Returns ``{"corner_share", "prior_share"}`` (the mean over action
    dimensions of the decoder's spread divided by the data's: 0 when the
    decoder ignores its latent, about 1 when the box spans the data's actions),
    and the per-dimension ``data_std``, ``corner_std``, ``prior_std`` lists.
    A goal-conditioned CVAE reads each state's goal from ``data``.
    """
    device = next(cvae.parameters()).device
    td = data.data
    n = td.shape[0]
    if n == 0:
        raise ValueError("decoder_sensitivity: no states to measure on")
    idx = torch.linspace(0, n - 1, min(num_states, n)).long()
    obs = td.get("observation")[idx].float().to(device)
    goal_key = getattr(cvae, "goal_key", None)
    goal = td.get(goal_key)[idx].float().to(device) if goal_key else None
    gen = torch.Generator().manual_seed(seed)
    prior = torch.randn(num_latents, obs.shape[0], cvae.latent_dim, generator=gen).to(device)
    corners = bound * torch.randint(0, 2, prior.shape, generator=gen).to(device, prior.dtype).mul(2).sub(1)

    def spread(latents):  # [L, S, Z] -> [A]: std over latents, mean over states (all L x S decoded in one batch)
        count = latents.shape[0]
        cond_goal = None if goal is None else goal.repeat(count, 1)
        actions = cvae.decoder(obs.repeat(count, 1), latents.reshape(-1, latents.shape[-1]), cond_goal)
        return actions.reshape(count, obs.shape[0], -1).std(0, unbiased=False).mean(0).double().cpu()

    data_std = td.get("action").double().std(0, unbiased=False).clamp_min(1e-12)
    corner, prior_std = spread(corners), spread(prior)
    return {"corner_share": float((corner / data_std).mean()), "prior_share": float((prior_std / data_std).mean()),
            "data_std": data_std.tolist(), "corner_std": corner.tolist(), "prior_std": prior_std.tolist()}
