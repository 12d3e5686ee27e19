import hashlib
import os

import h5py
import numpy as np
import pytest
import torch

from torchrl_offhrl.data import DatasetError, OfflineDataset, load_dataset, make_toy_dataset, save_dataset


def _md5(path):
    return hashlib.md5(open(path, "rb").read()).hexdigest()


def _write(path, **arrays):
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
    return path


def _d4rl_arrays(n=10, obs_dim=3, act_dim=2, next_obs=True):
    obs = np.arange(n * obs_dim, dtype=np.float32).reshape(n, obs_dim)
    out = {
        "observations": obs,
        "actions": np.ones((n, act_dim), np.float32) * 0.5,
        "rewards": np.arange(n, dtype=np.float32),
        # episode A: rows 0-3 ends terminal; B: rows 4-7 ends by timeout; C: rows 8-9 unfinished
        "terminals": np.array([0, 0, 0, 1, 0, 0, 0, 0, 0, 0], bool),
        "timeouts": np.array([0, 0, 0, 0, 0, 0, 0, 1, 0, 0], bool),
    }
    if next_obs:
        out["next_observations"] = obs + 1000
    return out


def test_d4rl_file_with_next_observations(tmp_path):
    path = _write(tmp_path / "d.hdf5", **_d4rl_arrays())
    ds = load_dataset(path)
    assert len(ds) == 10 and ds.num_episodes == 3
    td = ds.data
    assert td["next", "terminated"].squeeze(-1).tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 0, 0]
    # the file stops mid-episode: the last row becomes a truncation
    assert td["next", "truncated"].squeeze(-1).tolist() == [0, 0, 0, 0, 0, 0, 0, 1, 0, 1]
    assert td["episode"].tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2]
    assert torch.equal(td["next", "observation"], td["observation"] + 1000)
    assert td["next", "reward"].shape == (10, 1)


def test_d4rl_file_without_next_observations_derives_them(tmp_path):
    path = _write(tmp_path / "d.hdf5", **_d4rl_arrays(next_obs=False))
    ds = load_dataset(path)
    # rows 3 (terminal), 7 (timeout) and 9 (end of file) have no recorded successor
    assert len(ds) == 7
    assert ds.metadata["dropped_transitions"] == 3
    obs = ds.data["observation"][:, 0].tolist()
    nobs = ds.data["next", "observation"][:, 0].tolist()
    assert obs == [0, 3, 6, 12, 15, 18, 24]
    assert nobs == [3, 6, 9, 15, 18, 21, 27]  # the next row of the file, within each episode
    assert ds.num_episodes == 3
    assert ds.data["next", "truncated"].squeeze(-1).tolist() == [0, 0, 1, 0, 0, 1, 1]


def test_own_format_round_trip_with_metadata(tmp_path):
    ds = make_toy_dataset(num_episodes=4, episode_length=6)
    ds.metadata.update({"seed": 7, "returns": {"mean": 1.5}})
    path = save_dataset(ds, tmp_path / "sub" / "toy.hdf5")
    again = load_dataset(path)
    for key in ds.data.keys(True, True):
        assert torch.equal(again.data[key], ds.data[key]), key
    assert again.metadata["seed"] == 7 and again.metadata["returns"] == {"mean": 1.5}
    assert again.metadata["env_id"] == "Toy-v0"
    assert torch.equal(again.action_low, ds.action_low)
    assert not [p for p in os.listdir(path.parent) if p.endswith(".tmp")]


def test_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    ds = make_toy_dataset(num_episodes=2, episode_length=3)
    target = tmp_path / "x.hdf5"

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("torchrl_offhrl.data.io.json.dumps", boom)
    with pytest.raises(KeyboardInterrupt):
        save_dataset(ds, target)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing_key", r"missing key\(s\) \['rewards'\]"),
        ("length", r"key 'actions' has 9 rows"),
        ("nan", r"key 'observations' .* NaN/inf"),
        ("inf", r"key 'rewards' .* NaN/inf"),
        ("bad_next", r"'next_observations' has shape \(10, 4\)"),
        ("rank", r"key 'observations' has shape \(10,\)"),
    ],
)
def test_malformed_files_raise_and_are_not_modified(tmp_path, case, match):
    arrays = _d4rl_arrays()
    if case == "missing_key":
        del arrays["rewards"]
    elif case == "length":
        arrays["actions"] = arrays["actions"][:9]
    elif case == "nan":
        arrays["observations"][4, 1] = np.nan
    elif case == "inf":
        arrays["rewards"][2] = np.inf
    elif case == "bad_next":
        arrays["next_observations"] = np.zeros((10, 4), np.float32)
    elif case == "rank":
        arrays["observations"] = arrays["observations"][:, 0]
        del arrays["next_observations"]
    path = _write(tmp_path / f"{case}.hdf5", **arrays)
    before = _md5(path)
    with pytest.raises(DatasetError, match=match) as err:
        load_dataset(path)
    assert str(path) in str(err.value)
    assert _md5(path) == before


def test_not_hdf5_and_missing_path(tmp_path):
    p = tmp_path / "notes.hdf5"
    p.write_text("not an hdf5 file")
    with pytest.raises(DatasetError, match="is not an HDF5 file"):
        load_dataset(p)
    assert p.read_text() == "not an hdf5 file"
    with pytest.raises(DatasetError, match="no such file"):
        load_dataset(tmp_path / "nope.hdf5")


def test_dimension_mismatch_with_env(tmp_path):
    path = _write(tmp_path / "d.hdf5", **_d4rl_arrays())
    with pytest.raises(DatasetError, match="width 3 but Hopper-v5 observations have shape"):
        load_dataset(path, env_id="Hopper-v5")


def test_minari_local_dataset(tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    import gymnasium as gym

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    from minari.data_collector.episode_buffer import EpisodeBuffer

    env = gym.make("Pendulum-v1", max_episode_steps=20)
    env.action_space.seed(0)
    buffers = []
    for e in range(2):
        o, _ = env.reset(seed=e)
        obs, acts, rews, terms, truncs = [o], [], [], [], []
        for _ in range(20):
            a = env.action_space.sample()
            o, r, te, tr, _ = env.step(a)
            obs.append(o), acts.append(a), rews.append(r), terms.append(te), truncs.append(tr)
        buffers.append(
            EpisodeBuffer(
                id=e, observations=np.array(obs), actions=np.array(acts), rewards=np.array(rews),
                terminations=np.array(terms), truncations=np.array(truncs),
            )
        )
    minari.create_dataset_from_buffers(
        "test/pendulum/tiny-v0", buffer=buffers, env=env, eval_env=env, algorithm_name="random",
        author="tests", author_email="tests@localhost", code_permalink="tests/test_data.py",
        description="two random Pendulum episodes",
    )
    ds = load_dataset("test/pendulum/tiny-v0")
    assert len(ds) == 40 and ds.num_episodes == 2 and ds.observation_dim == 3
    assert ds.data["next", "truncated"].squeeze(-1).nonzero().flatten().tolist() == [19, 39]
    # within an episode the next observation is the following observation
    assert torch.allclose(ds.data["next", "observation"][:19], ds.data["observation"][1:20])
    assert ds.metadata["env_id"] == "Pendulum-v1"
    with pytest.raises(DatasetError, match="stored locally"):
        load_dataset("test/pendulum/absent-v0")


def test_stats_hand_computed():
    from tensordict import TensorDict

    td = TensorDict(
        {
            "observation": torch.tensor([[0.0], [2.0], [4.0]]),
            "action": torch.tensor([[-1.0], [0.0], [1.0]]),
            "next": {
                "observation": torch.tensor([[1.0], [4.0], [7.0]]),
                "reward": torch.tensor([[1.0], [2.0], [3.0]]),
                "terminated": torch.zeros(3, 1, dtype=torch.bool),
                "truncated": torch.tensor([[False], [False], [True]]),
            },
        },
        batch_size=[3],
    )
    s = OfflineDataset(td).stats()
    assert s.obs_mean.item() == pytest.approx(2.0) and s.obs_std.item() == pytest.approx(2.0)
    assert s.delta_mean.item() == pytest.approx(2.0) and s.delta_std.item() == pytest.approx(1.0)
    assert s.reward_mean.item() == pytest.approx(2.0)
    assert s.obs_min.item() == 0.0 and s.obs_max.item() == 7.0
    assert s.action_low.item() == -1.0 and s.action_high.item() == 1.0


def test_split_by_episode():
    ds = make_toy_dataset(num_episodes=20, episode_length=5)
    train, val = ds.split(0.1, seed=3)
    assert (len(train), len(val)) == (90, 10)
    tr, va = set(train.data["episode"].tolist()), set(val.data["episode"].tolist())
    assert tr.isdisjoint(va) and tr | va == set(range(20))
    train2, val2 = ds.split(0.1, seed=3)
    assert torch.equal(val2.data["episode"], val.data["episode"])
    with pytest.raises(ValueError):
        ds.split(1.5)


def test_concatenate_renumbers_episodes():
    a = make_toy_dataset(num_episodes=2, episode_length=3, seed=0)
    b = make_toy_dataset(num_episodes=3, episode_length=3, seed=1)
    c = OfflineDataset.concatenate([a, b])
    assert len(c) == 15 and c.num_episodes == 5
    assert c.data["episode"].tolist() == sum([[i] * 3 for i in range(5)], [])
    assert c.metadata["unfinished_episodes"] == [] and c.episode_returns(complete_only=True).numel() == 5
    # unfinished episodes follow the renumbering (ids given as the parts' own episode values)
    a.metadata["unfinished_episodes"], b.metadata["unfinished_episodes"] = [1], [0, 2]
    c = OfflineDataset.concatenate([a, b])
    assert c.metadata["unfinished_episodes"] == [1, 2, 4]
    torch.testing.assert_close(c.episode_returns(complete_only=True), c.episode_returns()[[0, 3]])
    st, rets = c.return_stats(), c.episode_returns()[[0, 3]]
    assert (st["episodes"], st["unfinished"], st["complete"]) == (2, 3, True)
    assert st["mean"] == pytest.approx(float(rets.mean())) and st["std"] == pytest.approx(float(rets.std()))
    # nothing finished: the stats fall back to the unfinished episodes and say so
    b.metadata["unfinished_episodes"] = [0, 1, 2]
    st = b.return_stats()
    assert (st["episodes"], st["unfinished"], st["complete"]) == (3, 3, False)
    assert st["mean"] == pytest.approx(float(b.episode_returns().mean()))


def test_collect_is_deterministic_and_consistent():
    from torchrl_offhrl.data import collect_dataset

    a = collect_dataset("Hopper-v5", 300, num_envs=2, seed=3, progress=False)
    b = collect_dataset("Hopper-v5", 300, num_envs=2, seed=3, progress=False)
    assert len(a) == 300
    for key in a.data.keys(True, True):
        assert torch.equal(a.data[key], b.data[key]), key
    # inside an episode, s'_t == s_{t+1}
    same_ep = a.data["episode"][1:] == a.data["episode"][:-1]
    assert torch.allclose(a.data["next", "observation"][:-1][same_ep], a.data["observation"][1:][same_ep])
    # every episode ends with done, and only there
    done = a.data["next", "done"].squeeze(-1)
    assert done[-1] and torch.equal(done[:-1], ~same_ep)
    # each stream's last episode is unfinished unless it ended at the last step (no 1000-step limit within 150 steps)
    ends = [149, 299]
    cut = [int(a.data["episode"][i]) for i in ends if not a.data["next", "terminated"][i]]
    assert a.metadata["unfinished_episodes"] == cut
    assert a.metadata["returns"]["episodes"] == a.num_episodes - len(cut) == a.episode_returns(complete_only=True).numel()
    c = collect_dataset("Hopper-v5", 300, num_envs=2, seed=4, progress=False)
    assert not torch.equal(a.data["action"], c.data["action"])


def test_concatenated_parts_stay_separate_after_save_load(tmp_path):
    from tensordict import TensorDict

    def part(n):
        return OfflineDataset(TensorDict({
            "observation": torch.zeros(n, 1), "action": torch.zeros(n, 1),
            "next": {"observation": torch.zeros(n, 1), "reward": torch.ones(n, 1),
                     "terminated": torch.zeros(n, 1, dtype=torch.bool),
                     "truncated": torch.zeros(n, 1, dtype=torch.bool)}},  # no final done flag
            batch_size=[n]))

    both = OfflineDataset.concatenate([part(3), part(4)])
    assert both.num_episodes == 2
    again = load_dataset(save_dataset(both, tmp_path / "c.hdf5"))
    assert again.num_episodes == 2 and again.episode_returns().tolist() == [3.0, 4.0]


def test_atomic_write_gives_default_permissions(tmp_path):
    import os

    from torchrl_offhrl.utils import atomic_write

    with atomic_write(tmp_path / "f.txt") as tmp:
        open(tmp, "w").write("x")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "f.txt").stat().st_mode & 0o777 == 0o666 & ~umask


# ------------------------------------------------ TensorDict-like access and replay buffers
def _numbered_dataset(n=12):
    """Row i has observation i, action -i and reward 10 i: a row's values name its index."""
    from tensordict import TensorDict

    idx = torch.arange(n, dtype=torch.float32)[:, None]
    td = TensorDict({
        "observation": idx.clone(), "action": -idx,
        "next": {"observation": idx + 1, "reward": 10 * idx,
                 "terminated": torch.zeros(n, 1, dtype=torch.bool),
                 "truncated": (torch.arange(n) % 4 == 3)[:, None]}},
        batch_size=[n])
    return OfflineDataset(td, metadata={"env_id": "Numbered-v0", "seed": 5, "returns": {"mean": 1.0}})


def _sorted_rows(td):
    """The transitions of ``td`` as sorted tuples of all their leaf values (a multiset of rows)."""
    keys = sorted(td.keys(True, True), key=str)
    flat = torch.cat([td[k].reshape(td.shape[0], -1).double().cpu() for k in keys], -1)
    return sorted(map(tuple, flat.tolist()))


def test_dataset_keys_and_indexing_match_the_tensordict():
    from tensordict import TensorDictBase

    ds = _numbered_dataset()
    td = ds.data
    assert list(ds.keys(True)) == list(td.keys(True))
    assert list(ds.keys()) == list(td.keys())
    assert list(ds.keys(True, True)) == list(td.keys(include_nested=True, leaves_only=True))
    assert list(ds.keys(include_nested=True, sort=True)) == list(td.keys(True, sort=True))
    assert ("next", "done") in ds.keys(True) and "episode" in ds.keys()
    assert "observation" in ds and ("next", "reward") in ds and "nope" not in ds and ("next", "nope") not in ds
    # keys return the stored tensors themselves
    assert ds["next", "reward"] is td.get(("next", "reward"))
    assert ds["observation"] is td.get("observation")
    assert ds["next", "reward"].squeeze(-1).tolist() == [10.0 * i for i in range(12)]
    # a mask picks exactly its rows, every key consistent
    mask = torch.tensor([1, 0, 0, 1, 1, 0, 0, 0, 1, 0, 1, 0], dtype=torch.bool)
    sub = ds[mask]
    assert isinstance(sub, TensorDictBase) and sub.batch_size == torch.Size([5])
    assert sub["observation"].squeeze(-1).tolist() == [0.0, 3.0, 4.0, 8.0, 10.0]
    assert sub["action"].squeeze(-1).tolist() == [-0.0, -3.0, -4.0, -8.0, -10.0]
    assert sub["next", "reward"].squeeze(-1).tolist() == [0.0, 30.0, 40.0, 80.0, 100.0]
    assert sub["next", "done"].squeeze(-1).tolist() == [False, True, False, False, False]
    assert sub["episode"].tolist() == [0, 0, 1, 2, 2]
    # int, slice, index tensor
    row = ds[7]
    assert row.batch_size == torch.Size([]) and row["observation"].item() == 7.0 and row["next", "reward"].item() == 70.0
    assert ds[2:5]["observation"].squeeze(-1).tolist() == [2.0, 3.0, 4.0]
    assert ds[torch.tensor([9, 1, 9])]["next", "observation"].squeeze(-1).tolist() == [10.0, 2.0, 10.0]
    assert len(ds) == 12 and ds.batch_size == torch.Size([12]) == td.batch_size
    assert ds.device == torch.device("cpu")


_DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]


@pytest.mark.parametrize("device", _DEVICES)
def test_dataset_to_device_keeps_metadata_and_values(device):
    ds = _numbered_dataset()
    ds.stats()
    moved = ds.to(device)
    assert isinstance(moved, OfflineDataset) and moved is not ds and moved.data is not ds.data
    assert moved.device.type == device and moved["observation"].device.type == device
    assert moved.metadata == ds.metadata and moved.metadata is not ds.metadata
    assert list(moved.keys(True)) == list(ds.keys(True))
    for key in ds.keys(True, True):
        assert torch.equal(moved[key].cpu(), ds[key]), key
    assert moved.action_low.device.type == device and torch.equal(moved.action_low.cpu(), ds.action_low)
    assert torch.equal(moved.action_high.cpu(), ds.action_high)
    assert moved.stats().obs_mean.device.type == device
    torch.testing.assert_close(moved.stats().obs_mean.cpu(), ds.stats().obs_mean)
    assert moved.num_episodes == ds.num_episodes == 3
    # the original is unchanged, and edits of the copy do not reach it
    moved.data.set("observation", torch.zeros_like(moved["observation"]))
    moved.metadata["seed"] = 99
    assert ds.device == torch.device("cpu") and ds["observation"].squeeze(-1).tolist() == list(map(float, range(12)))
    assert ds.metadata["seed"] == 5


def test_to_replay_buffer_samples_rows_of_the_dataset():
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    ds = make_toy_dataset(num_episodes=10, episode_length=30)  # 300 transitions, unique rows
    rb = ds.to_replay_buffer()
    assert isinstance(rb, ReplayBuffer) and isinstance(rb.storage, LazyTensorStorage)
    assert len(rb) == len(ds) == 300 and rb.storage.max_size == 300
    # the storage holds the dataset, row for row
    stored = rb.storage[:300]
    for key in ds.keys(True, True):
        assert torch.equal(stored[key], ds[key]), key
    torch.manual_seed(0)
    batch, info = rb.sample(return_info=True)
    assert batch.batch_size == torch.Size([256]) and batch.device == torch.device("cpu")
    assert sorted(batch.keys(True), key=str) == sorted(ds.keys(True), key=str)
    idx = info["index"]
    for key in ds.keys(True, True):
        assert torch.equal(batch[key], ds[key][idx]), key
    # the buffer is a copy: editing the dataset afterwards leaves it alone
    ds.data.get("observation").zero_()
    assert not torch.equal(rb.storage[:300]["observation"], ds["observation"])


def test_to_replay_buffer_without_replacement_covers_the_dataset_once():
    from torchrl.data import SamplerWithoutReplacement

    ds = make_toy_dataset(num_episodes=3, episode_length=20)
    rb = ds.to_replay_buffer(batch_size=len(ds), sampler=SamplerWithoutReplacement())
    batch = rb.sample()
    assert batch.batch_size == torch.Size([60])
    assert _sorted_rows(batch) == _sorted_rows(ds.data)
    assert len(set(_sorted_rows(ds.data))) == 60  # rows are distinct, so this is a permutation
    # batch_size=None leaves the size to sample(); a transform applies to every batch
    rb = ds.to_replay_buffer(batch_size=None, transform=lambda td: td.exclude("episode"))
    part = rb.sample(7)
    assert part.batch_size == torch.Size([7]) and "episode" not in part.keys()
    assert set(_sorted_rows(part)) <= set(_sorted_rows(ds.data.exclude("episode")))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_to_replay_buffer_on_cuda():
    ds = make_toy_dataset(num_episodes=2, episode_length=10)
    rb = ds.to_replay_buffer(batch_size=8, device="cuda")
    batch, info = rb.sample(return_info=True)
    assert batch.device.type == "cuda" and batch["observation"].device.type == "cuda"
    assert torch.equal(batch["observation"].cpu(), ds["observation"][info["index"].cpu()])
    on_gpu = ds.to("cuda").to_replay_buffer(batch_size=8)  # device=None: where the data lives
    assert on_gpu.sample()["action"].device.type == "cuda"


def test_to_replay_buffer_rejects_bad_input():
    ds = make_toy_dataset(num_episodes=4, episode_length=10)  # 40 transitions
    for bad in (0, -3):
        with pytest.raises(ValueError, match=rf"batch_size must be positive, got {bad}; pass the number"):
            ds.to_replay_buffer(batch_size=bad)
    with pytest.raises(ValueError, match=r"batch_size=41 is larger than the dataset \(40 transitions.*pass batch_size <= 40"):
        ds.to_replay_buffer(batch_size=41)
    with pytest.raises(ValueError, match=r"batch_size=256 is larger than the dataset"):
        ds.to_replay_buffer()  # the default is too large for this dataset
    for bad in (2.5, True, "8"):
        with pytest.raises(TypeError, match=r"batch_size must be an int in \[1, 40\]"):
            ds.to_replay_buffer(batch_size=bad)
    with pytest.raises(TypeError, match="sampler must be a torchrl.data.replay_buffers.Sampler"):
        ds.to_replay_buffer(batch_size=8, sampler="random")
    assert len(ds.to_replay_buffer(batch_size=40)) == 40  # the whole dataset is a valid batch


def test_returns_to_go_matches_the_backward_recursion():
    """The vectorised returns-to-go equal G_t = r_t + gamma G_{t+1} run episode by episode (long episodes, gamma 0.99 and 1)."""
    from torchrl_offhrl.data import make_toy_dataset

    ds = make_toy_dataset(num_episodes=4, episode_length=700, seed=3)
    r = ds.data["next", "reward"].squeeze(-1).double()
    starts = ds.episode_starts()
    for gamma in (0.99, 1.0, 0.0):
        expected = torch.zeros_like(r)
        acc = 0.0
        for i in reversed(range(r.numel())):
            last = i + 1 == r.numel() or bool(starts[i + 1])
            acc = float(r[i]) + (0.0 if last else gamma * acc)
            expected[i] = acc
        torch.testing.assert_close(ds.returns_to_go(gamma), expected, rtol=1e-9, atol=1e-7)
    with pytest.raises(ValueError, match="gamma"):
        ds.returns_to_go(1.5)
    with pytest.raises(ValueError, match="underflows"):  # 0.5 ** 1099 is below float64's range: a clear error, not NaN
        make_toy_dataset(num_episodes=1, episode_length=1100).returns_to_go(0.5)


@pytest.mark.fault("data")
def test_implausible_values_are_refused_with_the_key_and_index_and_an_opt_out(tmp_path, monkeypatch):
    """A few rewards at 1e30 (a glitch) are named on load; heavy-tailed and rare-event columns load; the opt-out loads anything."""
    from torchrl_offhrl.data import DatasetError, load_dataset, make_toy_dataset, save_dataset
    from torchrl_offhrl.data.dataset import TRUST_DATA_ENV

    monkeypatch.delenv(TRUST_DATA_ENV, raising=False)
    ds = make_toy_dataset(num_episodes=40, episode_length=50)
    rew = ds.data.get(("next", "reward"))
    torch.manual_seed(0)
    rew.copy_(torch.distributions.Cauchy(0.0, 1.0).sample(rew.shape))  # heavy tails: loads
    obs = ds.data.get("observation")
    obs[:, 0] = 0.0
    obs[::500, 0] = 9.0                                                 # a rare event in a column of zeros: loads
    good = tmp_path / "good.hdf5"
    save_dataset(ds, good)
    assert len(load_dataset(good)) == 2000
    rew[[7, 1234]] = 1e30
    bad = tmp_path / "bad.hdf5"
    save_dataset(ds, bad)
    with pytest.raises(DatasetError, match=r"key 'rewards' .* holds 2 implausible value\(s\), the first 1e\+30 at index \[7, 0\].*TORCHRL_OFFHRL_TRUST_DATA=1"):
        load_dataset(bad)
    monkeypatch.setenv(TRUST_DATA_ENV, "1")
    assert float(load_dataset(bad).data.get(("next", "reward")).max()) == pytest.approx(1e30, rel=1e-6)
