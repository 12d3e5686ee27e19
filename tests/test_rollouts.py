"""evaluate_policy's early stop: the same first episodes as the full rollout, fewer steps."""
import pytest
import torch

from torchrl_offhrl.data import load_policy, make_gym_env
from torchrl_offhrl.rollouts import evaluate_policy


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


def test_per_env_seeds_make_each_block_the_evaluation_of_its_own_seed():
    """Two blocks of 3 envs seeded 11, 12, 13 and 40, 41, 42 in one 6-env env start and run as two 3-env envs seeded 11 and 40
    (the falling linear policy: the same start states exactly, the same steps and returns to float32's rounding)."""
    from torchrl_offhrl.rollouts import seed_each_env

    policy = _linear_policy()
    both = make_gym_env("Hopper-v5", num_envs=6)
    rb, tb = evaluate_policy(both, policy, 6, max_steps=60, seed=0, env_seeds=[11, 12, 13, 40, 41, 42], return_rollout=True)
    for k, s in enumerate((11, 40)):
        alone = make_gym_env("Hopper-v5", num_envs=3)
        ra, ta = evaluate_policy(alone, policy, 3, max_steps=60, seed=s, return_rollout=True)
        block = tb[3 * k: 3 * k + 3]
        torch.testing.assert_close(block["observation"][:, 0], ta["observation"][:, 0], rtol=0, atol=0)  # the same start states
        t = ta.shape[1]
        torch.testing.assert_close(block["next", "observation"][:, :t], ta["next", "observation"], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(rb[3 * k: 3 * k + 3], ra, rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match="2 seeds for an env of batch size"):
        seed_each_env(both, [1, 2])
