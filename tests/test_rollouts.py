"""evaluate_policy's early stop: the same first episodes as the full rollout, fewer steps."""
import pytest
import torch

from torchrl_offhrl.data import load_policy, make_gym_env
from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask


def _both(policy, episodes: int, max_steps: int, deterministic: bool, seed: int = 5):
    env = make_gym_env("Hopper-v5", num_envs=episodes)
    full = evaluate_policy(env, policy, episodes, max_steps=max_steps, deterministic=deterministic, seed=seed, return_rollout=True, stop_early=False)
    short = evaluate_policy(env, policy, episodes, max_steps=max_steps, deterministic=deterministic, seed=seed, return_rollout=True)
    return full, short


def _linear_policy():
    """A deterministic policy that makes the hopper fall within a few hundred steps: tanh of fixed random weights."""
    from tensordict.nn import TensorDictModule

    g = torch.Generator().manual_seed(0)
    lin = torch.nn.Linear(11, 3)
    with torch.no_grad():
        lin.weight.copy_(torch.randn(3, 11, generator=g))
        lin.bias.zero_()
    return TensorDictModule(torch.nn.Sequential(lin, torch.nn.Tanh()), in_keys=["observation"], out_keys=["action"])


@pytest.mark.parametrize("deterministic", [True, False])
def test_stopping_early_keeps_every_first_episode_step(deterministic):
    """Random actions (policy None), a falling linear policy and the hopper-medium actor, sampled and deterministic: the
    stopped rollout is the full rollout's first T steps key for key, T is where the last env's first episode ends (or
    max_steps while one still runs), and the returns are equal."""
    actor, _ = load_policy("hopper-medium")
    stopped = 0
    for policy in (None, _linear_policy(), actor):
        if policy is None and deterministic:
            continue  # random actions have no deterministic mode
        (rf, tf), (rs, ts) = _both(policy, 4, 400, deterministic)
        # the same rewards summed over fewer (masked-out) steps: float32's vectorised sum may round the last digit apart
        torch.testing.assert_close(rs, rf, rtol=1e-6, atol=0.0)
        done = tf["next", "done"].reshape(4, -1)
        first_end = int(done.float().argmax(1).max()) + 1 if done.any(1).all() else 400
        assert ts.shape == (4, first_end)
        stopped += first_end < 400
        head = tf[:, :first_end]
        for key in head.keys(True, True):
            assert torch.equal(head[key], ts[key]), key
        alive = first_episode_mask(ts["next", "done"].reshape(4, -1))
        assert torch.equal((ts["next", "reward"].reshape(4, -1) * alive).sum(1), rs)
    assert stopped >= 1  # the falling policies stop early (the check above is not only of full-length rollouts)


def test_no_stop_while_an_episode_runs_and_none_without_a_seed():
    """An episode that outlasts max_steps keeps the rollout at max_steps; an unseeded call always runs max_steps (the env's
    state after it is the next call's start)."""
    actor, _ = load_policy("hopper-medium")
    (rf, tf), (rs, ts) = _both(actor, 2, 30, True)  # the medium policy does not fall within 30 steps
    assert ts.shape == tf.shape == (2, 30) and torch.equal(rf, rs)  # the same steps: the same sums
    env = make_gym_env("Hopper-v5", num_envs=2)
    env.set_seed(3)
    _, td = evaluate_policy(env, None, 2, max_steps=300, deterministic=False, seed=None, return_rollout=True)
    assert td.shape == (2, 300) and td["next", "done"].any(1).all()
