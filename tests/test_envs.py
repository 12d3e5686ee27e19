import pytest
import torch
from torchrl.envs import Compose, InitTracker, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_offhrl.envs import (
    LatentActionTransform,
    PessimisticModelEnv,
    calibrate_threshold,
    hopper_termination,
    termination_fn_for,
)


@pytest.fixture
def make_env(toy_data, fitted_ensemble):
    def make(**kw):
        kw.setdefault("seed", 0)
        return PessimisticModelEnv(fitted_ensemble, toy_data, **kw)

    return make


@pytest.mark.parametrize("batch_size", [[], [7], [2, 3]])
def test_specs_of_composed_env(make_env, fitted_cvae, batch_size):
    env = TransformedEnv(make_env(batch_size=batch_size, horizon=4), LatentActionTransform(fitted_cvae.decoder))
    check_env_specs(env)
    assert env.full_action_spec["latent_action"].shape == (*batch_size, 2)
    assert "action" in env.full_state_spec.keys()
    check_env_specs(make_env(batch_size=batch_size))


def test_out_of_distribution_actions_end_with_penalty(make_env):
    for kind in ("variance", "std", "max_pairwise"):
        env = make_env(batch_size=[512], penalty=7.0, discrepancy=kind)
        td = env.reset()
        g = torch.Generator().manual_seed(1)
        in_dist = (torch.rand(512, 2, generator=g) * 2 - 1) * 0.5  # the data's actions
        corners = torch.sign(torch.randn(512, 2, generator=g))  # inside the box, outside the data
        out_in = env.step(td.clone().set("action", in_dist))["next"]
        out_ood = env.step(td.clone().set("action", corners))["next"]
        assert out_in["penalized"].float().mean() < 0.05, kind
        assert out_ood["penalized"].float().mean() > 0.95, kind
        pen = out_ood["penalized"].squeeze(-1)
        assert (out_ood["reward"][pen] == -7.0).all()
        assert out_ood["terminated"][pen].all() and out_ood["done"][pen].all()
        assert not out_ood["truncated"][pen].any()
        ok = ~out_in["penalized"].squeeze(-1)
        assert (out_in["reward"][ok] > -7.0).all() and not out_in["terminated"][ok].any()


def test_reward_penalty_subtracts_lambda_times_discrepancy(make_env, fitted_ensemble):
    # the same start states, members and actions with and without the soft penalty: rewards differ by exactly
    # reward_penalty x the step's discrepancy (MOPO's r - lambda u), hand-computed from the ensemble's own prediction
    g = torch.Generator().manual_seed(3)
    act = (torch.rand(64, 2, generator=g) * 2 - 1) * 0.8
    plain, soft = make_env(batch_size=[64], threshold=float("inf")), make_env(batch_size=[64], threshold=float("inf"), reward_penalty=2.5)
    td0, td1 = plain.reset(), soft.reset()
    assert torch.equal(td0["observation"], td1["observation"]) and torch.equal(td0["model_member"], td1["model_member"])
    out0 = plain.step(td0.set("action", act))["next"]
    out1 = soft.step(td1.set("action", act))["next"]
    pred = fitted_ensemble.predict(td0["observation"], act)
    disc = fitted_ensemble.discrepancy_of(pred["delta"], "variance")
    assert disc.min() > 0
    torch.testing.assert_close(out0["reward"] - out1["reward"], 2.5 * disc.unsqueeze(-1))
    torch.testing.assert_close(out1["discrepancy"], disc.unsqueeze(-1))
    # a pessimistic termination still pays exactly -penalty, not -penalty - lambda u
    hard = make_env(batch_size=[64], threshold=-1.0, penalty=3.0, reward_penalty=2.5)
    assert (hard.step(hard.reset().set("action", act))["next", "reward"] == -3.0).all()
    with pytest.raises(ValueError, match="reward_penalty must be >= 0"):
        make_env(reward_penalty=-1.0)


def test_explicit_threshold_extremes(make_env):
    env = make_env(batch_size=[16], threshold=-1.0, penalty=3.0)  # every step violates
    td = env.rollout(1)
    assert (td["next", "reward"] == -3.0).all() and td["next", "terminated"].all()
    assert env.calibration.method == "explicit" and env.calibration.fraction_above == 1.0
    env = make_env(batch_size=[16], threshold=float("inf"))
    td = env.rollout(5, break_when_any_done=False)
    assert not td["next", "penalized"].any()


def test_nan_and_out_of_bounds_predictions_never_propagate(make_env, fitted_ensemble, monkeypatch):
    env = make_env(batch_size=[4], threshold=float("inf"), penalty=5.0)
    td = env.reset()
    real_predict = fitted_ensemble.predict

    def broken(obs, act):
        out = real_predict(obs, act)
        nobs = out["next_observation"].clone()
        nobs[:, 0] = float("nan")  # env 0: NaN
        nobs[:, 1] = 1e6  # env 1: far outside the data's bounds
        out["next_observation"] = nobs
        return out

    monkeypatch.setattr(fitted_ensemble, "predict", broken)
    out = env.step(td.clone().set("action", torch.zeros(4, 2)))["next"]
    assert torch.isfinite(out["observation"]).all()
    assert out["penalized"].squeeze(-1).tolist() == [True, True, False, False]
    assert torch.equal(out["observation"][:2], td["observation"][:2])  # kept at the last known state
    assert out["reward"][:2].squeeze(-1).tolist() == [-5.0, -5.0]


def test_truncation_at_horizon(make_env):
    env = make_env(batch_size=[3], threshold=float("inf"), horizon=4)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "model_step"][:, -1].squeeze(-1).tolist() == [4, 4, 4]
    assert td["next", "truncated"][:, -1].all() and not td["next", "terminated"].any()
    assert not td["next", "truncated"][:, :-1].any()


def test_partial_reset_only_touches_masked_envs(make_env):
    env = make_env(batch_size=[6], threshold=float("inf"))
    td = env.reset()
    for _ in range(3):
        td = env.step(td.set("action", torch.zeros(6, 2)))
        from torchrl.envs.utils import step_mdp

        td = step_mdp(td)
    before = td.clone()
    mask = torch.tensor([True, False, True, False, False, True]).unsqueeze(-1)
    after = env.reset(td.clone().set("_reset", mask))
    m = mask.squeeze(-1)
    assert torch.equal(after["observation"][~m], before["observation"][~m])
    assert torch.equal(after["model_member"][~m], before["model_member"][~m])
    assert after["model_step"][m].eq(0).all() and after["model_step"][~m].eq(3).all()
    starts = env.start_states
    # reset envs start from an episode start state of the dataset
    for row in after["observation"][m]:
        assert (starts == row).all(-1).any()


def test_cyclic_member_draw_gives_every_member_its_share(make_env):
    env = make_env(batch_size=[7], threshold=float("inf"), horizon=5, member_draw="cyclic")
    k = env.num_members
    expected = torch.arange(7) % k
    for _ in range(2):  # at every reset, env i uses member i % K
        td = env.rollout(6, break_when_any_done=False)
        assert torch.equal(td["model_member"][:, 0].squeeze(-1), expected)
        assert (td["model_member"].squeeze(-1) == expected[:, None]).all()  # kept through auto-resets
    with pytest.raises(ValueError, match="member_draw"):
        make_env(batch_size=[2], member_draw="round")


def test_member_modes(make_env):
    env = make_env(batch_size=[64], threshold=float("inf"), horizon=50)
    td = env.rollout(20, break_when_any_done=False)
    member = td["model_member"].squeeze(-1)
    assert (member == member[:, :1]).all()  # one member per episode
    assert member[:, 0].unique().numel() > 1  # drawn independently per env
    # the selected member's prediction is the next state
    env1 = make_env(batch_size=[8], threshold=float("inf"))
    t = env1.reset()
    a = torch.zeros(8, 2)
    out = env1.step(t.clone().set("action", a))
    pred = env1.ensemble.predict(t["observation"], a)["next_observation"]
    rows = torch.arange(8)
    assert torch.allclose(out["next", "observation"], pred[t["model_member"].squeeze(-1), rows])
    envm = make_env(batch_size=[8], threshold=float("inf"), member_mode="mean")
    t = envm.reset()
    out = envm.step(t.clone().set("action", a))
    pred = envm.ensemble.predict(t["observation"], a)["next_observation"].mean(0)
    assert torch.allclose(out["next", "observation"], pred)


def test_seeding_reproduces_rollouts(make_env):
    a = make_env(batch_size=[5], seed=3).rollout(5, break_when_any_done=False)
    b = make_env(batch_size=[5], seed=3).rollout(5, break_when_any_done=False, policy=None)
    assert torch.equal(a["observation"][:, 0], b["observation"][:, 0])
    env = make_env(batch_size=[5])
    env.set_seed(11)
    x = env.reset()["observation"]
    env.set_seed(11)
    assert torch.equal(env.reset()["observation"], x)


def test_calibration_quantile_and_fraction(toy_data, fitted_ensemble, tmp_path):
    rep = calibrate_threshold(fitted_ensemble, toy_data, quantile=0.95)
    assert rep.fraction_above == pytest.approx(0.05, abs=0.002)
    rep = calibrate_threshold(fitted_ensemble, toy_data, fraction=1.08, quantile=0.5)
    assert rep.threshold == pytest.approx(1.08 * rep.disc_max) and rep.fraction_above == 0.0
    png = rep.plot(tmp_path / "h.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    env = PessimisticModelEnv(fitted_ensemble, toy_data, batch_size=[2])
    assert env.calibration.method == "quantile" and env.calibration.value == 0.99
    assert "threshold" in env.calibration_report()


def test_bad_arguments(toy_data, fitted_ensemble):
    with pytest.raises(ValueError, match="discrepancy must be one of"):
        PessimisticModelEnv(fitted_ensemble, toy_data, discrepancy="stdev")
    with pytest.raises(ValueError, match="member_mode"):
        PessimisticModelEnv(fitted_ensemble, toy_data, member_mode="random")
    with pytest.raises(ValueError, match="quantile must be in"):
        PessimisticModelEnv(fitted_ensemble, toy_data, quantile=1.5)


def test_hopper_termination_matches_gymnasium():
    """On real Hopper-v5 transitions, our function agrees with the env's own termination."""
    from torchrl_offhrl.data import collect_dataset

    ds = collect_dataset("Hopper-v5", 2000, num_envs=4, seed=0, progress=False)
    ours = hopper_termination(ds.data["next", "observation"])
    theirs = ds.data["next", "terminated"].squeeze(-1)
    assert theirs.sum() > 20
    assert torch.equal(ours, theirs)
    assert termination_fn_for("Hopper-v5") is hopper_termination
    assert not termination_fn_for("HalfCheetah-v5")(torch.full((2, 17), 1e3)).any()


def test_latent_transform_decodes_and_keeps_action(make_env, fitted_cvae):
    dec = fitted_cvae.decoder
    for chain in (False, True):
        base = make_env(batch_size=[4], horizon=3)
        latent = LatentActionTransform(dec, latent_bound=1.5)
        env = TransformedEnv(base, Compose(latent, StepCounter(), InitTracker())) if chain else TransformedEnv(base, latent)
        td = env.rollout(10, break_when_any_done=False)  # resets mid-rollout
        expect = dec(td["observation"], td["latent_action"].clamp(-1.5, 1.5))
        assert torch.allclose(td["action"], expect, atol=1e-6), chain
        check_env_specs(env)


def test_latent_transform_clip_and_errors(make_env, fitted_cvae):
    env = TransformedEnv(make_env(batch_size=[2]), LatentActionTransform(fitted_cvae.decoder, latent_bound=1.0))
    td = env.reset().set("latent_action", torch.full((2, 2), 50.0))
    out = env.step(td)
    assert torch.allclose(out["action"], fitted_cvae.decoder(td["observation"], torch.ones(2, 2)))
    env2 = TransformedEnv(make_env(batch_size=[2]), LatentActionTransform(fitted_cvae.decoder, clip=False))
    td = env2.reset().set("latent_action", torch.full((2, 2), 50.0))
    assert torch.allclose(env2.step(td)["action"], fitted_cvae.decoder(td["observation"], torch.full((2, 2), 50.0)))
    with pytest.raises(KeyError, match="must write 'latent_action'"):
        env.step(env.reset().set("action", torch.zeros(2, 2)))
    with pytest.raises(ValueError):
        LatentActionTransform(fitted_cvae.decoder, latent_bound=0)


def test_latent_transform_on_real_gym_env():
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.models import ConditionalVAE

    cvae = ConditionalVAE(11, 3, hidden_sizes=(16,))
    env = make_gym_env("Hopper-v5", num_envs=2)
    env.append_transform(LatentActionTransform(cvae.decoder))
    check_env_specs(env)
    td = env.rollout(30, break_when_any_done=False)
    assert torch.allclose(td["action"], cvae.decoder(td["observation"], td["latent_action"].clamp(-2, 2)), atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda(toy_data, fitted_ensemble, fitted_cvae):
    env = TransformedEnv(
        PessimisticModelEnv(fitted_ensemble, toy_data, batch_size=[32], device="cuda", seed=0),
        LatentActionTransform(fitted_cvae.decoder),
    ).to("cuda")
    td = env.rollout(5, break_when_any_done=False)
    assert td.device.type == "cuda" and torch.isfinite(td["next", "observation"]).all()


@pytest.mark.parametrize("chain, loop", [(False, "step_mdp"), (False, "maybe_reset"), (True, "maybe_reset")])
def test_hand_written_loop_keeps_every_decoded_action(make_env, fitted_cvae, chain, loop):
    """Manual loops: stored actions are right and never share storage across steps."""
    dec = fitted_cvae.decoder
    base = make_env(batch_size=[3], horizon=4)
    latent = LatentActionTransform(dec)
    env = TransformedEnv(base, Compose(latent, StepCounter())) if chain else TransformedEnv(base, latent)
    td = env.reset()
    kept = []
    for _ in range(6):
        td["latent_action"] = torch.randn(3, 2)
        if loop == "step_mdp":
            td = env.step(td)
            kept.append(td)
            td = env.step_mdp(td)
        else:
            out, td = env.step_and_maybe_reset(td)
            kept.append(out)
    stacked = torch.stack(kept, 1)
    expect = dec(stacked["observation"], stacked["latent_action"].clamp(-2, 2))
    assert torch.allclose(stacked["action"], expect, atol=1e-6)
    assert len({t["action"].data_ptr() for t in kept}) == len(kept)


def test_compose_with_step_mdp_loop_warns(make_env, fitted_cvae):
    env = TransformedEnv(make_env(batch_size=[3]), Compose(LatentActionTransform(fitted_cvae.decoder), StepCounter()))
    td = env.reset()
    with pytest.warns(RuntimeWarning, match="step_and_maybe_reset"):
        for _ in range(2):
            td["latent_action"] = torch.randn(3, 2)
            td = env.step_mdp(env.step(td))


def test_transform_leaves_the_decoder_trainable(fitted_cvae):
    LatentActionTransform(fitted_cvae.decoder)
    assert all(p.requires_grad for p in fitted_cvae.decoder.parameters())
    assert fitted_cvae.decoder.training == fitted_cvae.training


def test_step_mode_reports_the_member_it_used(make_env):
    env = make_env(batch_size=[64], threshold=float("inf"), member_mode="step", horizon=50)
    td = env.reset()
    a = torch.zeros(64, 2)
    out = env.step(td.clone().set("action", a))["next"]
    used = out["model_member"].squeeze(-1)
    pred = env.ensemble.predict(td["observation"], a)["next_observation"]
    assert torch.allclose(out["observation"], pred[used, torch.arange(64)])
    roll = env.rollout(10, break_when_any_done=False)["next", "model_member"].squeeze(-1)
    assert (roll != roll[:, :1]).any()  # redrawn within episodes


def test_chunked_prediction_is_the_same_step(make_env, fitted_ensemble):
    # more envs than the CPU chunk: the ensemble predicts them in chunks, with the values of one batch
    obs, act = torch.randn(70, fitted_ensemble.observation_dim), torch.rand(70, 2) - 0.5
    whole, parts = fitted_ensemble.predict(obs, act), fitted_ensemble.predict(obs, act, chunk=16)
    for k in ("next_observation", "reward", "delta"):
        assert parts[k].shape == whole[k].shape
        torch.testing.assert_close(parts[k], whole[k])
    a, b = make_env(batch_size=[70], threshold=float("inf")), make_env(batch_size=[70], threshold=float("inf"))
    b.predict_chunk = 16
    act = torch.rand(70, 2) - 0.5
    out_a, out_b = a.step(a.reset().set("action", act))["next"], b.step(b.reset().set("action", act))["next"]
    for k in ("observation", "reward", "discrepancy"):
        torch.testing.assert_close(out_b[k], out_a[k])


class _ZeroAgent:
    """An agent whose deterministic policy always acts 0 (what Evaluator.model_metrics rolls out)."""

    @staticmethod
    def eval_policy(td):
        return td.set("action", torch.zeros(*td.batch_size, 2))


@pytest.mark.parametrize("case, length, penalized, terminated", [
    ("pessimism", 1.0, 1.0, 0.0),  # threshold below every discrepancy: the first step ends every episode with the penalty
    ("fall", 1.0, 0.0, 1.0),  # the task's terminal states everywhere: the first step ends it, not the pessimism
    ("horizon", 6.0, 0.0, 0.0),  # neither: the model env's horizon ends it
])
def test_the_evaluation_says_where_model_episodes_end(make_env, case, length, penalized, terminated):
    from torchrl_offhrl.recipes.evaluation import Evaluator

    kw = {"pessimism": dict(threshold=-1.0), "fall": dict(threshold=float("inf"), termination_fn=lambda obs: torch.ones(obs.shape[:-1], dtype=torch.bool)),
          "horizon": dict(threshold=float("inf"), termination_fn=None, horizon=6)}[case]
    env = make_env(batch_size=[8], **kw)
    out = Evaluator(None, "toy", episodes=8, max_steps=20, seed=0, model_env=env).model_metrics(_ZeroAgent(), real_mean=0.0)
    assert (out["model_episode_length_mean"], out["model_penalized"], out["model_terminated"]) == (length, penalized, terminated)
