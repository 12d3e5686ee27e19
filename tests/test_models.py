import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.models import (
    ConditionalVAE,
    DynamicsEnsemble,
    EnsembleLinear,
    EnsembleMLP,
    SupervisedTrainer,
)


def test_ensemble_linear_matches_member_loop():
    torch.manual_seed(0)
    layer = EnsembleLinear(4, 6, 3)
    x = torch.randn(4, 10, 6)
    out = layer(x)
    for k in range(4):
        ref = torch.nn.functional.linear(x[k], layer.weight[k].T, layer.bias[k, 0])
        assert torch.allclose(out[k], ref, atol=1e-6)
    shared = torch.randn(10, 6)
    assert torch.allclose(layer(shared), layer(shared.expand(4, 10, 6)))
    with pytest.raises(ValueError, match=r"\[4, B, 6\]"):
        layer(torch.randn(3, 10, 6))


def test_members_are_initialised_differently_and_flops():
    net = EnsembleMLP(5, 14, 11, hidden_sizes=(512, 512))
    w = net.net[0].weight
    assert not torch.allclose(w[0], w[1])
    assert net.flops_per_sample() == 2 * 5 * (14 * 512 + 512 * 512 + 512 * 11)


def test_gradients_reach_each_member_independently():
    torch.manual_seed(0)
    net = EnsembleMLP(3, 4, 2, hidden_sizes=(8,))
    x = torch.randn(3, 5, 4)
    out = net(x)
    # a loss on member 1 only: no gradient leaks into members 0 and 2
    out[1].pow(2).sum().backward()
    for p in net.parameters():
        assert p.grad[1].abs().sum() > 0
        assert p.grad[0].abs().sum() == 0 and p.grad[2].abs().sum() == 0
    # the gradient of the summed losses equals each member's own gradient
    net.zero_grad()
    losses = net(x).pow(2).flatten(1).sum(-1)
    losses.sum().backward()
    summed = [p.grad.clone() for p in net.parameters()]
    for k in range(3):
        net.zero_grad()
        net(x)[k].pow(2).sum().backward()
        for g, p in zip(summed, net.parameters()):
            assert torch.allclose(g[k], p.grad[k], atol=1e-5)


def test_discrepancy_hand_computed():
    # 3 members, 1 pair, 2 dims
    delta = torch.tensor([[[0.0, 0.0]], [[3.0, 0.0]], [[0.0, 4.0]]])
    var = DynamicsEnsemble.discrepancy_of(delta, "variance")
    # per-dim population variance: dim0 of {0,3,0} = 2, dim1 of {0,0,4} = 32/9
    assert var.item() == pytest.approx(2.0 + 32.0 / 9.0)
    std = DynamicsEnsemble.discrepancy_of(delta, "std")
    assert std.item() == pytest.approx((2.0 + 32.0 / 9.0) ** 0.5)  # the norm of the members' standard deviations
    mp = DynamicsEnsemble.discrepancy_of(delta, "max_pairwise")
    assert mp.item() == pytest.approx(5.0)  # |(3,0) - (0,4)|
    with pytest.raises(ValueError, match="discrepancy must be one of"):
        DynamicsEnsemble.discrepancy_of(delta, "bogus")


class _Spy(torch.nn.Module):
    """Records the minibatches each member sees."""

    num_members = 3
    train_keys = ("x",)

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(3, 1))
        self.seen = []

    def loss(self, batch):
        x = batch["x"]
        if x.dim() == 2:
            self.seen.append(x.clone())
            return (self.w - x.float().mean(-1, keepdim=True)).pow(2).squeeze(-1)
        return (self.w.squeeze(-1) - x.float().mean()).pow(2)


def test_trainer_draws_independent_bootstrap_batches():
    spy = _Spy()
    data = TensorDict({"x": torch.arange(1000)}, batch_size=[1000])
    SupervisedTrainer(lr=1e-2, batch_size=64, max_epochs=1, steps_per_epoch=5, progress=False).fit(spy, data)
    batch = spy.seen[0]
    assert batch.shape == (3, 64)
    assert not torch.equal(batch[0], batch[1]) and not torch.equal(batch[1], batch[2])
    # with replacement over the whole set: indices are valid and repeats are allowed
    assert batch.min() >= 0 and batch.max() < 1000


def test_fit_learns_and_restores_best_weights(toy_data, fitted_ensemble):
    hist = fitted_ensemble.training_history
    first = torch.tensor(hist[0]["val_loss"])
    best = torch.tensor([h["val_loss"] for h in hist]).min(0).values
    assert (best < 0.5 * first).all(), (first, best)
    # after fit every member holds the weights of its own best validation epoch
    _, val = toy_data.split(0.1, seed=0)
    now = SupervisedTrainer().evaluate(fitted_ensemble, val.data)
    assert torch.allclose(now, best, rtol=1e-4, atol=1e-6)


def test_predictions_are_accurate_on_toy_dynamics(toy_data, fitted_ensemble):
    td = toy_data.data[:200]
    out = fitted_ensemble.predict(td["observation"], td["action"])
    err = (out["next_observation"] - td["next", "observation"]).abs().mean()
    spread = (td["next", "observation"] - td["observation"]).abs().mean()
    assert err < 0.2 * spread
    rerr = (out["reward"] - td["next", "reward"].squeeze(-1)).abs().mean()
    assert rerr < 0.2 * td["next", "reward"].abs().mean()


def test_early_stopping_with_patience():
    class Flat(_Spy):
        def loss(self, batch):  # nothing to learn: the loss never improves after epoch 0
            return self.w.squeeze(-1).detach() * 0 + 1.0 + 0 * self.w.squeeze(-1)

    data = TensorDict({"x": torch.arange(100)}, batch_size=[100])
    hist = SupervisedTrainer(max_epochs=50, steps_per_epoch=1, patience=3, progress=False).fit(Flat(), data, data)
    assert len(hist) == 4  # epoch 0 sets the best, then 3 epochs without improvement


def _gaussian_ensemble(toy_data, seed):
    torch.manual_seed(seed)
    return DynamicsEnsemble.for_dataset(toy_data, num_models=3, hidden_sizes=(32,), loss="nll")


@pytest.mark.fault("resume")
def test_a_killed_fit_resumes_from_its_checkpoint_to_the_weights_of_an_uninterrupted_fit(toy_data, tmp_path):
    train, val = toy_data.split(0.1, seed=0)
    settings = dict(lr=1e-3, batch_size=32, max_epochs=6, steps_per_epoch=10, patience=100, seed=3, progress=False)
    whole = _gaussian_ensemble(toy_data, 0)
    history = SupervisedTrainer(**settings).fit(whole, train.data, val.data)

    ckpt = tmp_path / "ensemble.fit.pt"
    with pytest.raises(KeyboardInterrupt):  # killed 35 steps in (in epoch 4), after the checkpoint of epoch 3 was written
        SupervisedTrainer(**settings, checkpoint=ckpt, checkpoint_every_s=0).fit(_dies_after(_gaussian_ensemble(toy_data, 0), 35),
                                                                                   train.data, val.data)
    assert ckpt.is_file()
    restarted = _dies_after(_gaussian_ensemble(toy_data, 1), 10**9)  # a new process: other initial weights, the checkpoint's win
    resumed = SupervisedTrainer(**settings, checkpoint=ckpt, checkpoint_every_s=0).fit(restarted, train.data, val.data)
    assert restarted.calls == 30  # epochs 4-6 only
    assert [h["epoch"] for h in resumed] == list(range(6)) and resumed == history
    for (name, a), b in zip(whole.state_dict().items(), restarted.state_dict().values()):
        assert torch.equal(a, b), name
    assert not ckpt.exists() and not ckpt.with_name(ckpt.name + ".sha256").exists()  # the fit is over: no state left behind


def _dies_after(model, steps):
    """``model``, whose loss raises KeyboardInterrupt (a kill) once it has been called ``steps`` times; counts the calls."""
    loss, model.calls = model.loss, 0

    def counted(batch):
        model.calls += 1
        if model.calls > steps:
            raise KeyboardInterrupt
        return loss(batch)

    model.loss = counted
    return model


@pytest.mark.fault("resume")
def test_a_checkpoint_of_another_fit_is_set_aside_not_resumed(toy_data, tmp_path):
    train, val = toy_data.split(0.1, seed=0)
    settings = dict(lr=1e-3, batch_size=32, max_epochs=2, steps_per_epoch=5, patience=100, progress=False)
    ckpt = tmp_path / "ensemble.fit.pt"
    with pytest.raises(KeyboardInterrupt):  # a fit on half the data, killed in its second epoch: its checkpoint stays
        SupervisedTrainer(**settings, checkpoint=ckpt, checkpoint_every_s=0).fit(
            _dies_after(_gaussian_ensemble(toy_data, 0), 7), train.data[: len(train.data) // 2], val.data)
    assert ckpt.is_file()
    fresh = _dies_after(_gaussian_ensemble(toy_data, 0), 10**9)
    with pytest.warns(UserWarning, match="written by another fit"):
        history = SupervisedTrainer(**settings, checkpoint=ckpt).fit(fresh, train.data, val.data)
    assert len(history) == 2 and fresh.calls == 10  # both epochs run: from scratch
    assert ckpt.with_name(ckpt.name + ".stale").is_file() and not ckpt.exists()


@pytest.mark.parametrize("loss", ["mse", "nll"])
def test_other_losses_train(toy_data, loss):
    torch.manual_seed(0)
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(32,), loss=loss)
    ens.fit(toy_data, lr=1e-3, max_epochs=8, progress=False)
    h = ens.training_history
    assert torch.tensor(h[-1]["val_loss"]).mean() < torch.tensor(h[0]["val_loss"]).mean()
    out = ens.predict(toy_data[:3]["observation"], toy_data[:3]["action"])
    assert out["next_observation"].shape == (2, 3, 3)


def test_known_reward_function(toy_data):
    fn = lambda obs, act, nobs: -(nobs**2).sum(-1)  # noqa: E731
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(8,), learn_reward=False, reward_fn=fn)
    assert ens.reward_net is None
    out = ens.predict(toy_data[:4]["observation"], toy_data[:4]["action"])
    assert torch.allclose(out["reward"], -(out["next_observation"] ** 2).sum(-1))
    # a reward of the current state only, [N], is shared by every member
    ens.reward_fn = lambda obs, act, nobs: -(obs**2).sum(-1)  # noqa: E731
    out = ens.predict(toy_data[:4]["observation"], toy_data[:4]["action"])
    assert out["reward"].shape == (2, 4)
    assert torch.equal(out["reward"][0], out["reward"][1])
    assert torch.allclose(out["reward"][0], -(toy_data[:4]["observation"] ** 2).sum(-1))


def test_save_load_round_trip(tmp_path, fitted_ensemble, fitted_cvae, toy_data):
    obs, act = toy_data[:5]["observation"], toy_data[:5]["action"]
    p = fitted_ensemble.save(tmp_path / "ens.pt")
    blob = torch.load(p, weights_only=True)  # plain tensors and Python values only
    assert blob["class"] == "DynamicsEnsemble"
    again = DynamicsEnsemble.load(p)
    a, b = fitted_ensemble.predict(obs, act), again.predict(obs, act)
    assert torch.equal(a["next_observation"], b["next_observation"]) and torch.equal(a["reward"], b["reward"])
    c = ConditionalVAE.load(fitted_cvae.save(tmp_path / "cvae.pt"))
    z = torch.randn(5, c.latent_dim)
    assert torch.equal(c.decoder(obs, z), fitted_cvae.decoder(obs, z))
    with pytest.raises(ValueError, match="not a ConditionalVAE"):
        ConditionalVAE.load(p)
    with pytest.raises(FileNotFoundError):
        DynamicsEnsemble.load(tmp_path / "missing.pt")


def test_cvae_decoder_stays_in_action_box(toy_data, fitted_cvae):
    obs = toy_data[:100]["observation"]
    a = fitted_cvae.decoder(obs, 1e3 * torch.randn(100, fitted_cvae.latent_dim))
    assert (a >= toy_data.action_low).all() and (a <= toy_data.action_high).all()


def test_cvae_reconstructs_state_dependent_actions():
    """Actions that are a function of the state: the CVAE must learn the mapping."""
    from torchrl_offhrl.data import OfflineDataset

    torch.manual_seed(0)
    n = 4000
    obs = torch.rand(n, 2) * 2 - 1
    act = torch.tanh(torch.stack([obs[:, 0] + obs[:, 1], obs[:, 0] - obs[:, 1]], -1)) * 0.8
    td = TensorDict(
        {"observation": obs, "action": act, "next": {"observation": obs, "reward": torch.zeros(n, 1),
         "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": (torch.arange(n) % 20 == 19)[:, None]}},
        batch_size=[n],
    )
    ds = OfflineDataset(td, action_bounds=(-torch.ones(2), torch.ones(2)))
    cvae = ConditionalVAE.for_dataset(ds, hidden_sizes=(64, 64)).fit(ds, lr=3e-3, max_epochs=30, progress=False)
    # decoding the prior mean gives the behaviour action for that state
    pred = cvae.decoder(obs[:500], torch.zeros(500, 2))
    assert (pred - act[:500]).abs().mean() < 0.1


def test_goal_conditioned_cvae(toy_data):
    data = toy_data
    data.data.set("desired_goal", torch.randn(len(data), 2))
    cvae = ConditionalVAE.for_dataset(data, goal_key="desired_goal", hidden_sizes=(16,))
    cvae.fit(data, max_epochs=1, progress=False)
    obs, g = data[:3]["observation"], data[:3]["desired_goal"]
    assert cvae.decoder(obs, torch.zeros(3, 2), g).shape == (3, 2)
    with pytest.raises(ValueError, match="goal-conditioned"):
        cvae.decoder(obs, torch.zeros(3, 2))
    data.data.del_("desired_goal")


# ---------------------------------------------------------------- MOPO's Gaussian ensemble (issue 72)
def _constant_members(ens, means, raw_logvars, reward_means=None, reward_raw_logvars=None):
    """Zero every weight so that member k outputs its bias: ``means[k]`` and ``raw_logvars[k]`` (normalised units)."""
    with torch.no_grad():
        for p in ens.parameters():
            p.zero_() if p.dim() == 3 and p.shape[1] != 1 else None
        ens.dynamics.net[-1].bias.copy_(torch.cat([torch.tensor(means), torch.tensor(raw_logvars)], -1).unsqueeze(1))
        if reward_means is not None:
            ens.reward_net.net[-1].bias.copy_(torch.tensor([[m, v] for m, v in zip(reward_means, reward_raw_logvars)]).unsqueeze(1))
        for head in ens.max_logvar:
            ens.max_logvar[head].fill_(0.5)
            ens.min_logvar[head].fill_(-10.0)


def _softly_bounded(v, hi=0.5, lo=-10.0):
    import math

    sp = lambda x: math.log1p(math.exp(x))  # noqa: E731
    v = hi - sp(hi - v)
    return lo + sp(v - lo)


def test_the_learned_log_variance_bounds_squash_as_mopo_does_and_are_pulled_together(toy_data):
    """A raw log-variance far above the upper bound comes out at it, far below the lower one at it, 0 at the hand-computed
    value; the loss is mean((mu - y)^2 exp(-v) + v) + 0.01 (sum max - sum min), hand-computed on a constant member; and a
    fit moves the bounds (they are trained)."""
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(4,), loss="nll", learn_reward=False)
    d = toy_data.observation_dim
    _constant_members(ens, [[0.0] * d, [1.0] * d], [[100.0] * d, [-100.0] * d])
    x = torch.zeros(1, d + toy_data.action_dim)
    mean, logvar = ens._split(ens.dynamics(x))
    assert torch.allclose(logvar[0], torch.full((1, d), 0.5), atol=1e-4) and torch.allclose(logvar[1], torch.full((1, d), -10.0), atol=1e-4)
    _constant_members(ens, [[0.0] * d, [0.0] * d], [[0.0] * d, [0.0] * d])
    v0 = _softly_bounded(0.0)
    assert abs(v0 - (-0.4741)) < 1e-3 and torch.allclose(ens._split(ens.dynamics(x))[1], torch.full((2, 1, d), v0), atol=1e-5)
    # the loss on one pair whose normalised target is 1 in every dimension: (0 - 1)^2 e^-v0 + v0, + 0.01 (0.5 d - (-10) d)
    obs = torch.zeros(1, d)
    target_delta = ens.delta_mean + ens.delta_std  # a residual of exactly one delta_std above the mean: target 1
    batch = TensorDict({"observation": obs, "action": torch.zeros(1, toy_data.action_dim),
                        ("next", "observation"): obs + target_delta, ("next", "reward"): torch.zeros(1)}, batch_size=[1])
    import math

    want = (math.exp(-v0) + v0) + 0.01 * (0.5 * d + 10.0 * d)
    assert torch.allclose(ens.loss(batch), torch.full((2,), want), atol=1e-4)
    assert torch.allclose(ens.val_loss(batch), torch.ones(2), atol=1e-5)  # held-out error: the mean's squared error only
    fitted = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(16,), loss="nll")
    fitted.fit(toy_data, lr=1e-2, max_epochs=3, progress=False)
    for head in ("dynamics", "reward"):  # each head's own bounds are trained (the reward's by the reward's loss)
        assert not torch.allclose(fitted.max_logvar[head], torch.full_like(fitted.max_logvar[head], 0.5)), head
        assert not torch.allclose(fitted.min_logvar[head], torch.full_like(fitted.min_logvar[head], -10.0)), head


def test_the_elites_are_the_members_with_the_lowest_held_out_error(toy_data, tmp_path):
    """Four untrained members, two of them spoiled: with num_elites=2 and no learning (lr 0) the fit keeps the two good ones, best
    first; the pruned ensemble predicts as those members did, records what it kept, and saves and loads as a 2-member one."""
    torch.manual_seed(0)
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=4, hidden_sizes=(16,), loss="nll", num_elites=2)
    with torch.no_grad():
        ens.dynamics.net[-1].bias[1] += 50.0  # members 1 and 3 now predict far off
        ens.dynamics.net[-1].bias[3] += 80.0
    val = toy_data.split(0.1, seed=0)[1].data
    errors = ens.val_loss(val.select(*ens.train_keys))
    obs, act = toy_data[:5]["observation"], toy_data[:5]["action"]
    before = ens.predict(obs, act)["next_observation"]
    ens.fit(toy_data, lr=0.0, max_epochs=1, progress=False)  # lr 0: the weights stay; only the elites are chosen
    order = [int(i) for i in errors.argsort()[:2]]
    assert sorted(order) == [0, 2] and ens.config["elites"]["kept"] == order and ens.config["elites"]["trained"] == 4
    assert ens.num_models == 2 and ens.config["num_models"] == 2 and ens.max_logvar["dynamics"].shape[0] == 2
    assert torch.allclose(ens.predict(obs, act)["next_observation"], before[order], atol=1e-6)
    again = DynamicsEnsemble.load(ens.save(tmp_path / "elites.pt"))
    assert again.num_models == 2 and torch.allclose(again.predict(obs, act)["next_observation"], before[order], atol=1e-6)
    with pytest.raises(ValueError, match="num_elites must be between 2 and num_models"):
        DynamicsEnsemble.for_dataset(toy_data, num_models=4, num_elites=5, loss="nll")


def test_mopos_penalty_is_the_largest_norm_of_the_members_predicted_std(toy_data):
    """Hand-made members: raw log-variances 0 and log 4 (stds 1 and 2 in normalised units), the reward's 0 and 0: in the data's
    units member k's std is std_k * delta_std (state) and std_k * reward_std (reward), and the penalty is the larger norm."""
    import math

    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(4,), loss="nll")
    d = toy_data.observation_dim
    with torch.no_grad():
        for head in ens.max_logvar:  # wide bounds: the squashing leaves these values (nearly) as they are
            ens.max_logvar[head].fill_(20.0)
            ens.min_logvar[head].fill_(-20.0)
        for p in ens.parameters():
            if p.dim() == 3 and p.shape[1] != 1:
                p.zero_()
        ens.dynamics.net[-1].bias.copy_(torch.tensor([[0.0] * d + [0.0] * d, [0.0] * d + [math.log(4.0)] * d]).unsqueeze(1))
        ens.reward_net.net[-1].bias.copy_(torch.tensor([[0.0, 0.0], [0.0, 0.0]]).unsqueeze(1))
    obs, act = toy_data[:3]["observation"], toy_data[:3]["action"]
    pred = ens.predict(obs, act)
    std_k = torch.tensor([1.0, 2.0])
    norms = torch.stack([torch.cat([s * ens.delta_std, ens.reward_std]).norm() for s in std_k])
    want = norms.max().expand(3)
    assert torch.allclose(pred["std"][1, 0, :d], 2.0 * ens.delta_std, rtol=1e-4)
    assert torch.allclose(ens.discrepancy_of(pred["delta"], "aleatoric", pred["std"]), want, rtol=1e-4)
    assert torch.allclose(ens.discrepancy(obs, act, "aleatoric"), want, rtol=1e-4)
    l1 = DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(4,))
    with pytest.raises(ValueError, match="loss='nll'"):
        l1.discrepancy(obs, act, "aleatoric")
    from torchrl_offhrl.envs import PessimisticModelEnv

    with pytest.raises(ValueError, match="predicts none"):
        PessimisticModelEnv(l1, toy_data, discrepancy="aleatoric", threshold=1.0)


class _KnownEnsemble(torch.nn.Module):
    """Two members predicting the true next state shifted by +1 and +3 state-change stds, the reward by +0 and +2."""

    def __init__(self, data):
        super().__init__()
        self.data, self.w = data, torch.nn.Parameter(torch.zeros(1))
        self.delta_std = (data.data["next", "observation"] - data.data["observation"]).std(0)

    def predict(self, obs, act):
        rows = (obs[:, None, :] == self.data.data["observation"][None]).all(-1).float().argmax(-1)  # the pairs' own rows
        nxt, rew = self.data.data["next", "observation"][rows], self.data.data["next", "reward"][rows].reshape(-1)
        shifts = torch.tensor([1.0, 3.0])[:, None, None] * self.delta_std
        return {"next_observation": nxt + shifts, "reward": rew + torch.tensor([0.0, 2.0])[:, None]}


def test_ensemble_quality_on_members_wrong_by_known_amounts(toy_data):
    from torchrl_offhrl.models import ensemble_quality

    q = ensemble_quality(_KnownEnsemble(toy_data), toy_data, chunk=97)  # chunks that do not divide the data
    # the mean is wrong by 2 stds in every dimension, the members spread by 1 (population std of 1 and 3)
    assert q["state_error"] == pytest.approx(2.0) and q["state_spread"] == pytest.approx(1.0)
    assert q["error_over_spread"] == pytest.approx(2.0)
    assert q["reward_error"] == pytest.approx(1.0) and q["reward_spread"] == pytest.approx(1.0)
    assert q["pairs"] == toy_data.data.shape[0]


class _Decoder(torch.nn.Module):
    def __init__(self, uses_latent):
        super().__init__()
        self.uses_latent = uses_latent

    def forward(self, obs, z, goal=None):
        return z[..., :2] if self.uses_latent else obs[..., :2] * 0.5


class _CVAE(torch.nn.Module):
    latent_dim, goal_key = 3, None

    def __init__(self, uses_latent):
        super().__init__()
        self.decoder, self.w = _Decoder(uses_latent), torch.nn.Parameter(torch.zeros(1))


def test_decoder_sensitivity_is_zero_for_a_collapsed_decoder_and_the_box_for_an_identity_one(toy_data):
    from torchrl_offhrl.models import decoder_sensitivity

    collapsed = decoder_sensitivity(_CVAE(False), toy_data, bound=2.0)
    assert collapsed["corner_share"] == 0.0 and collapsed["prior_share"] == 0.0
    identity = decoder_sensitivity(_CVAE(True), toy_data, bound=2.0, num_latents=400)
    data_std = toy_data.data["action"].double().std(0, unbiased=False)
    # the action is the latent: at random corners of [-2, 2] its std is ~2 (random signs), from N(0, I) ~1
    assert identity["corner_std"] == pytest.approx([2.0, 2.0], rel=0.02)
    assert identity["prior_std"] == pytest.approx([1.0, 1.0], rel=0.03)
    assert identity["corner_share"] == pytest.approx(float((2.0 / data_std).mean()), rel=0.02)


@pytest.mark.fault("resume")
def test_a_checkpoint_whose_data_sums_differ_in_the_last_bits_is_resumed(toy_data, tmp_path):
    """A float64 sum over many values depends on the order of its additions (the thread count): a fit killed under one
    thread count and resumed under another must not be thrown away for sums equal to 1e-9. The data's bytes decide."""
    from torchrl_offhrl.models.trainer import _same_fit

    train, val = toy_data.split(0.1, seed=0)
    trainer = SupervisedTrainer(lr=1e-3, batch_size=32, max_epochs=2, steps_per_epoch=5, progress=False)
    ens = _gaussian_ensemble(toy_data, 0)
    params = [p for p in ens.parameters() if p.requires_grad]
    here = trainer._fingerprint(train.data.select(*ens.train_keys), len(val.data), ens.num_members, params)
    there = {**here, "data_sums": [x * (1 + 3e-16) + 1e-13 for x in here["data_sums"]]}  # other rounding, same data
    assert _same_fit(there, here)
    assert not _same_fit({**there, "data_sums": [x + 1.0 for x in here["data_sums"]]}, here)  # other sums
    assert not _same_fit({**here, "data_digest": "0" * 64}, here)  # other bytes, the same sums
    old = {k: v for k, v in there.items() if k != "data_digest"}  # written before the digest: judged on the sums
    assert _same_fit(old, here) and not _same_fit({**old, "lr": 1.0}, here)
    changed = train.data.clone()
    changed["action"][0, 0] += 1e-3  # one value: the sums barely move, the digest does
    other = trainer._fingerprint(changed.select(*ens.train_keys), len(val.data), ens.num_members, params)
    assert other["data_digest"] != here["data_digest"] and not _same_fit(other, here)


def test_a_sampling_model_env_steps_each_member_mean_plus_its_std_times_the_envs_noise(toy_data):
    """MOPO's step (model_env.sample): next state and reward = the member's mean + its predicted std x standard normal noise,
    the noise drawn from the env's generator (replayed here by hand); without sampling, the member's mean; an ensemble
    without predicted stds is refused."""
    import pytest
    import torch

    from torchrl_offhrl.envs import PessimisticModelEnv
    from torchrl_offhrl.models import DynamicsEnsemble

    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=3, hidden_sizes=(16,), loss="nll").fit(toy_data, max_epochs=2, progress=False)
    kw = dict(threshold=float("inf"), penalty=0.0, termination_fn=None, horizon=5, member_mode="step", batch_size=[6], seed=3)
    mean_env, sampling_env = PessimisticModelEnv(ens, toy_data, **kw), PessimisticModelEnv(ens, toy_data, sample=True, **kw)
    td = sampling_env.reset()
    td["action"] = torch.rand(6, toy_data.action_dim) * 2 - 1
    rng = torch.Generator().manual_seed(0)
    rng.set_state(sampling_env._rng.get_state())  # the generator's state before the step: the member draw, then the noise
    out = sampling_env.step(td.clone())["next"]
    member = torch.randint(0, 3, (6,), generator=rng)
    pred = ens.predict(td["observation"], td["action"])
    rows = torch.arange(6)
    std = pred["std"][member, rows]
    noise = torch.randn(std.shape, generator=rng) * std
    d = toy_data.observation_dim
    assert torch.allclose(out["observation"], pred["next_observation"][member, rows] + noise[:, :d], atol=1e-5)
    assert torch.allclose(out["reward"].reshape(-1), pred["reward"][member, rows] + noise[:, d], atol=1e-5)
    assert (noise.abs() > 0).all()
    mean_env._rng.set_state(sampling_env._rng.get_state())
    td2 = mean_env.reset()
    td2["action"] = td["action"]
    state = mean_env._rng.get_state()
    plain = mean_env.step(td2.clone())["next"]
    rng.set_state(state)
    member2 = torch.randint(0, 3, (6,), generator=rng)
    pred2 = ens.predict(td2["observation"], td2["action"])
    assert torch.allclose(plain["observation"], pred2["next_observation"][member2, rows], atol=1e-6)  # the mean, no noise
    with pytest.raises(ValueError, match="sample=True draws from a member's Gaussian"):
        PessimisticModelEnv(DynamicsEnsemble.for_dataset(toy_data, num_models=2, hidden_sizes=(8,)), toy_data, sample=True, **kw)
