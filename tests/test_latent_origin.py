"""The latent origin (model_env.latent_origin=best | behaviour): an agent's latent 0 decodes to the (best) data's action at each state."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.models import ConditionalVAE, CVAEDecoder, LatentOrigin


def _state_dependent_data(n=4000, seed=0):
    """Actions a deterministic function of the state (one behaviour policy)."""
    from torchrl_offhrl.data import OfflineDataset

    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 2, generator=g) * 2 - 1
    act = torch.tanh(torch.stack([obs[:, 0] + obs[:, 1], obs[:, 0] - obs[:, 1]], -1)) * 0.8
    td = TensorDict(
        {"observation": obs, "action": act, "next": {"observation": obs, "reward": torch.zeros(n, 1),
         "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": (torch.arange(n) % 20 == 19)[:, None]}},
        batch_size=[n],
    )
    return OfflineDataset(td, action_bounds=(-torch.ones(2), torch.ones(2)))


class _Const(LatentOrigin):
    """An origin that puts every state at the same latent (hand-computable)."""

    def __init__(self, value, condition_dim=2, latent_dim=2):
        super().__init__(condition_dim, latent_dim, hidden_sizes=(4,))
        self.value = torch.as_tensor(value, dtype=torch.float32)

    def forward(self, condition):
        return self.value.expand(*condition.shape[:-1], self.latent_dim)


def test_the_decoder_shifts_latents_by_the_origin_and_clamps_the_sum_to_the_box():
    torch.manual_seed(0)
    dec = CVAEDecoder(observation_dim=2, action_dim=2, latent_dim=2, hidden_sizes=(8,))
    obs, z = torch.randn(5, 2), torch.tensor([[0.5, -0.25]]).expand(5, 2)
    plain = dec(obs, torch.tensor([[1.0, -0.75]]).expand(5, 2))
    dec.set_origin(_Const([0.5, -0.5]), bound=2.0)
    assert torch.allclose(dec(obs, z), plain)                      # decoder(s, origin + z)
    assert torch.allclose(dec(obs, torch.zeros(5, 2)), dec.set_origin(None)(obs, torch.tensor([[0.5, -0.5]]).expand(5, 2)))
    learned = LatentOrigin(2, 2, (4,))
    dec.set_origin(learned, bound=2.0).double()                    # moved with the decoder, though not a submodule
    assert learned.net[0].weight.dtype == torch.float64 and dec.origin is learned
    dec.float().set_origin(_Const([1.5, -1.5]), bound=2.0)         # 1.5 + 1.0 = 2.5 -> 2.0; -1.5 - 1.0 -> -2.0
    assert torch.allclose(dec(obs, torch.tensor([[1.0, -1.0]]).expand(5, 2)), dec.set_origin(None)(obs, torch.tensor([[2.0, -2.0]]).expand(5, 2)))


def test_the_origin_is_not_part_of_the_saved_cvae(tmp_path, toy_data, fitted_cvae):
    keys = set(fitted_cvae.state_dict())
    origin = fitted_cvae.fit_origin(toy_data, hidden_sizes=(16,), max_epochs=2, progress=False)
    fitted_cvae.decoder.set_origin(origin, 2.0)
    try:
        assert set(fitted_cvae.state_dict()) == keys and origin not in list(fitted_cvae.modules())
        back = ConditionalVAE.load(fitted_cvae.save(tmp_path / "cvae.pt"))
        assert back.decoder.origin is None
        with pytest.raises(ValueError, match="conditions on"):
            fitted_cvae.decoder.set_origin(LatentOrigin(7, fitted_cvae.latent_dim, (4,)))
    finally:
        fitted_cvae.decoder.set_origin(None)


def test_the_origin_regresses_the_posterior_means_it_is_given():
    """A known target: the posterior means a linear function of the conditioning input."""
    from torchrl_offhrl.data import OfflineDataset

    ds = _state_dependent_data(n=2000)
    torch.manual_seed(0)
    cond = ds.data["observation"]
    target = cond @ torch.tensor([[1.0, -2.0], [0.5, 0.0]]) + torch.tensor([0.25, -0.5])
    td = ds.data.clone(False)
    td.set("latent_condition", cond)
    td.set("latent_target", target)
    origin = LatentOrigin(2, 2, (32,)).fit(OfflineDataset(td, action_bounds=(ds.action_low, ds.action_high)), lr=1e-2, max_epochs=40,
                                            progress=False, seed=0)
    with torch.no_grad():
        assert (origin(cond) - target).abs().mean() < 0.05


def test_apply_latent_origin_fits_once_caches_beside_the_cvae_and_zero_restores_the_decoder(tmp_path, toy_data, fitted_cvae):
    from torchrl_offhrl.recipes.pipeline import apply_latent_origin

    cfg = {"seed": 0, "dataset": {"val_ratio": 0.1}, "cvae": {"hidden_sizes": [16], "fit": {"lr": 1e-3, "max_epochs": 2}},
           "env": {"latent_origin": "behaviour", "latent_bound": 2.0}}
    obs = toy_data[:8]["observation"]
    try:
        first, info = apply_latent_origin(cfg, toy_data, fitted_cvae, tmp_path, progress=False)
        assert (tmp_path / "latent_origin.pt").is_file() and fitted_cvae.decoder.origin is first and info is None
        a = fitted_cvae.decoder(obs, torch.zeros(8, fitted_cvae.latent_dim))
        second, _ = apply_latent_origin(cfg, None, fitted_cvae, tmp_path, progress=False)  # loaded: no data needed
        assert second is not first and torch.equal(fitted_cvae.decoder(obs, torch.zeros(8, fitted_cvae.latent_dim)), a)
        assert apply_latent_origin({**cfg, "env": {"latent_origin": "zero"}}, toy_data, fitted_cvae, tmp_path) == (None, None)
        with pytest.raises(FileNotFoundError, match="latent_origin.pt is missing"):
            apply_latent_origin(cfg, None, fitted_cvae, tmp_path / "elsewhere", progress=False)
        assert fitted_cvae.decoder.origin is None
        with pytest.raises(ValueError, match="best, behaviour, zero"):
            apply_latent_origin({**cfg, "env": {"latent_origin": "mean"}}, toy_data, fitted_cvae, tmp_path)
        # best: its own cache entry, fitted on the top-return episodes only, which the report's info names
        best, info = apply_latent_origin({**cfg, "env": {"latent_origin": "best", "origin_share": 0.25, "latent_bound": 2.0}}, toy_data,
                                         fitted_cvae, tmp_path, progress=False)
        assert (tmp_path / "latent_origin_top0.25.pt").is_file() and best is not first and fitted_cvae.decoder.origin is best
        assert info["share"] == 0.25 and info["transitions_kept"] >= 0.25 * len(toy_data) and info["episodes_kept"] < info["episodes"]
    finally:
        fitted_cvae.decoder.set_origin(None)


def _two_behaviours(n_ep=10, length=20):
    """Episodes of two behaviours on the same states: even episodes act +0.8 with reward 1 per step, odd ones -0.8 with reward 0."""
    from torchrl_offhrl.data import OfflineDataset

    g = torch.Generator().manual_seed(0)
    n = n_ep * length
    obs = torch.rand(n, 2, generator=g) * 2 - 1
    good = ((torch.arange(n) // length) % 2 == 0)[:, None]
    act = torch.where(good, 0.8, -0.8).expand(n, 2).clone()
    td = TensorDict({"observation": obs, "action": act, "next": {"observation": obs, "reward": good.float(),
                     "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": (torch.arange(n) % length == length - 1)[:, None]}},
                    batch_size=[n])
    return OfflineDataset(td, action_bounds=(-torch.ones(2), torch.ones(2)))


def test_top_return_episodes_takes_whole_episodes_best_first_until_the_share_is_covered():
    from torchrl_offhrl.data import OfflineDataset

    # four episodes of lengths 3, 5, 2, 4 (14 transitions) with returns 3, 10, 8, 1 (one reward per episode, at its end)
    lengths, rets = [3, 5, 2, 4], [3.0, 10.0, 8.0, 1.0]
    n = sum(lengths)
    reward = torch.zeros(n, 1)
    ends = torch.cumsum(torch.tensor(lengths), 0) - 1
    reward[ends, 0] = torch.tensor(rets)
    trunc = torch.zeros(n, 1, dtype=torch.bool)
    trunc[ends, 0] = True
    td = TensorDict({"observation": torch.zeros(n, 1), "action": torch.zeros(n, 1), "next": {"observation": torch.zeros(n, 1),
                     "reward": reward, "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": trunc}}, batch_size=[n])
    ds = OfflineDataset(td)
    mask, info = ds.top_return_episodes(0.3)          # 4.2 transitions: the best episode (5) covers it
    assert mask.tolist() == [False] * 3 + [True] * 5 + [False] * 6 and info["episodes_kept"] == 1 and info["return_kept_mean"] == 10.0
    mask, info = ds.top_return_episodes(0.5)          # 7 transitions: 5 + 2 (returns 10 and 8)
    assert mask.tolist() == [False] * 3 + [True] * 7 + [False] * 4 and info["transitions_kept"] == 7 and info["return_kept_mean"] == 9.0
    mask, info = ds.top_return_episodes(1.0)
    assert bool(mask.all()) and info["episodes_kept"] == 4 and info["return_mean"] == 5.5
    with pytest.raises(ValueError, match="share"):
        ds.top_return_episodes(0.0)


def test_the_best_origin_clones_the_higher_return_behaviour_where_the_behaviour_origin_averages_the_two(tmp_path):
    """Two behaviours on the same states (+0.8 rewarded, -0.8 not): decoded at the origin regressed on all the data the agent's
    latent 0 acts between the two, at the origin regressed on the best half it acts as the rewarded behaviour."""
    from torchrl_offhrl.models import ConditionalVAE
    from torchrl_offhrl.recipes.pipeline import fit_or_load_origin

    ds = _two_behaviours(n_ep=20, length=50)
    torch.manual_seed(0)
    cvae = ConditionalVAE(2, 2, hidden_sizes=(32, 32), kl_weight=0.05).fit(ds, max_epochs=100, lr=3e-3, patience=100, progress=False, seed=0)
    cfg = {"seed": 0, "dataset": {"val_ratio": 0.1}, "cvae": {"hidden_sizes": [32], "fit": {"lr": 3e-3, "max_epochs": 60}}}
    all_origin, _ = fit_or_load_origin(cfg, ds, cvae, tmp_path, progress=False, share=1.0)
    best_origin, info = fit_or_load_origin(cfg, ds, cvae, tmp_path, progress=False, share=0.5)
    assert info["episodes_kept"] == 10 and info["return_kept_mean"] == 50.0 and info["return_mean"] == 25.0
    obs, z = ds.data["observation"][:200], torch.zeros(200, 2)
    try:
        with torch.no_grad():
            best = cvae.decoder.set_origin(best_origin, 2.0)(obs, z)
            average = cvae.decoder.set_origin(all_origin, 2.0)(obs, z)
        assert (best - 0.8).abs().mean() < 0.1          # the rewarded behaviour's action
        assert (average - 0.8).abs().mean() > 0.5 and (average + 0.8).abs().mean() > 0.5  # neither behaviour's
    finally:
        cvae.decoder.set_origin(None)


def test_the_default_uses_the_best_origin_and_the_paper_preset_the_prior_mean():
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.schema import validate_config
    from torchrl_offhrl.utils import to_plain

    default = to_plain(compose("offline_train", ["env=hopper"]))["model_env"]
    assert default["latent_origin"] == "best" and default["origin_share"] == 0.1
    assert to_plain(compose("offline_train", ["env=hopper", "preset=paper"]))["model_env"]["latent_origin"] == "zero"
    assert to_plain(compose("offline_train", ["env=blockstack2"]))["model_env"]["latent_origin"] == "zero"
    with pytest.raises(ValueError, match="latent_origin"):
        validate_config(to_plain(compose("offline_train", ["env=hopper", "model_env.latent_origin=mean"])))
    with pytest.raises(ValueError, match="origin_share"):
        validate_config(to_plain(compose("offline_train", ["env=hopper", "model_env.origin_share=0"])))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_origin_follows_the_decoder_to_cuda(toy_data, fitted_cvae):
    origin = fitted_cvae.fit_origin(toy_data, hidden_sizes=(16,), max_epochs=2, progress=False)
    dec = fitted_cvae.decoder
    try:
        dec.set_origin(origin, 2.0)
        cpu = dec(toy_data[:4]["observation"], torch.zeros(4, fitted_cvae.latent_dim))
        dec.cuda()
        gpu = dec(toy_data[:4]["observation"].cuda(), torch.zeros(4, fitted_cvae.latent_dim, device="cuda"))
        assert origin.net[0].weight.is_cuda and torch.allclose(gpu.cpu(), cpu, atol=1e-5)
    finally:
        dec.cpu().set_origin(None)


def test_the_shipped_ppo_starts_at_the_latent_origin_as_moc_does():
    """algo.head_gain=0.01 (ppo.yaml): the untrained actor's deterministic latent is ~0, which the behaviour origin decodes to
    the data's action; TorchRL's initialisation (1.0) starts it O(1) away, a random policy in the decoder's box."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env({"env": {"threshold": 1.0}}, DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
                         ConditionalVAE.for_dataset(d, hidden_sizes=(8,)), d, batch_size=64)
    td = env.reset()
    spread = {}
    for gain in (0.01, 1.0):
        torch.manual_seed(0)
        agent = make_agent("ppo", env, hidden_sizes=[64, 64], head_gain=gain)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            spread[gain] = float(agent.eval_policy(td.clone())["latent_action"].abs().max())
    assert spread[0.01] < 0.05 < spread[1.0], spread
    with pytest.raises(ValueError, match="head_gain"):
        make_agent("ppo", env, hidden_sizes=[8], head_gain=0.0)
