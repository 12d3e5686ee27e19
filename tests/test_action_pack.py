"""Action packs: a generated dataset rebuilt bit for bit from its actions; anything else refused."""
from pathlib import Path

import pytest
import torch

from torchrl_offhrl.data import DatasetError, generate_dataset, make_toy_dataset
from torchrl_offhrl.data.action_pack import load_action_pack, save_action_pack
from conftest import load_script


@pytest.fixture(scope="module")
def small_hopper():
    # uniform random actions, 4 streams of 150 steps: many falls inside each stream, so many unseeded resets to replay
    return generate_dataset("hopper", "random", num_transitions=600, seed=3, num_envs=4, progress=False, ref_episodes=0)


def test_the_rebuilt_dataset_is_the_generated_one(small_hopper, tmp_path):
    pack = save_action_pack(small_hopper, tmp_path / "p.pt")
    rebuilt = load_action_pack(pack, workers=2, progress=False)
    assert rebuilt.content_hash() == small_hopper.content_hash()
    for key in small_hopper.data.keys(True, True):
        assert torch.equal(rebuilt.data[key], small_hopper.data[key]), key
    done = small_hopper.data["next", "done"].squeeze(-1)
    assert done.sum() > 12  # more episode ends than the 4 cut streams: resets inside a stream were replayed too
    assert torch.equal(rebuilt.action_low, small_hopper.action_low) and rebuilt.metadata["rebuilt_from_actions"] is True
    assert pack.stat().st_size < 0.5 * small_hopper.data.bytes()  # the actions alone


def test_streams_that_end_their_episodes_together_are_replayed_as_collected(tmp_path):
    """HalfCheetah's episodes all last 1000 steps, so every stream ends one at the same step, where the collector reset the
    whole vector env once more: the replay finds those steps and resets there twice, and gets the same bytes."""
    ds = generate_dataset("halfcheetah", "random", num_transitions=2200, seed=1, num_envs=2, progress=False, ref_episodes=0)
    trunc = ds.data["next", "truncated"].squeeze(-1).reshape(2, -1)
    assert trunc[:, 999].all()  # both streams' first episodes end at the same step
    rebuilt = load_action_pack(save_action_pack(ds, tmp_path / "hc.pt"), workers=2, progress=False)
    assert rebuilt.content_hash() == ds.content_hash()


def test_a_pack_whose_replay_differs_is_refused(small_hopper, tmp_path):
    from torchrl_offhrl.data.action_pack import _compress, read_action_pack

    state = read_action_pack(save_action_pack(small_hopper, tmp_path / "p.pt"))
    actions = state["actions"].clone()
    actions[10, 0] = -actions[10, 0]  # one action changed: the replayed data (and its hash) differ
    state["actions"] = _compress(actions)
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(DatasetError, match="replaying the actions gave other data"):
        load_action_pack(tmp_path / "bad.pt", workers=1, progress=False)


def test_what_cannot_be_packed_or_unpacked(tmp_path):
    with pytest.raises(DatasetError, match="one collection"):
        save_action_pack(make_toy_dataset(num_episodes=2, episode_length=5), tmp_path / "toy.pt")
    torch.save({"actions": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(DatasetError, match="not an action pack"):
        load_action_pack(tmp_path / "other.pt")
    (tmp_path / "junk.pt").write_text("not a torch file")
    with pytest.raises(DatasetError, match="not readable as an action pack"):
        load_action_pack(tmp_path / "junk.pt")


def test_unpack_puts_the_dataset_where_named_dataset_finds_it(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    from torchrl_offhrl.data import named_dataset

    mod = load_script("action_pack")
    original = named_dataset("hopper-medium-400", progress=False)  # generated, then cached
    path = Path(original.metadata["source"])
    assert mod.main(["pack", "hopper-medium-400", str(tmp_path / "hm.pt")]) == 0
    path.unlink()
    assert mod.main(["unpack", str(tmp_path / "hm.pt"), "--workers", "2"]) == 0
    assert path.is_file() and named_dataset("hopper-medium-400", progress=False).content_hash() == original.content_hash()
    # unpacked again onto the same data: found before any replay
    monkeypatch.setattr("torchrl_offhrl.data.action_pack.load_action_pack", lambda *a, **k: pytest.fail("replayed data already in the cache"))
    assert mod.main(["unpack", str(tmp_path / "hm.pt")]) == 0


def test_packed_actions_are_compressed_without_loss_and_old_packs_still_read(small_hopper, tmp_path):
    from torchrl_offhrl.data.action_pack import _compress, _decompress, read_action_pack

    pack = save_action_pack(small_hopper, tmp_path / "p.pt")
    stored = torch.load(pack, weights_only=True)["actions"]
    raw = small_hopper.data["action"].float()
    assert stored["zlib"].numel() < raw.numel() * 4  # fewer bytes than the float32 actions
    read = read_action_pack(pack)["actions"]
    assert read.dtype == torch.float32 and torch.equal(read, raw)
    # every bit pattern survives, not only the policy's: signed zeros, subnormals, infinities and NaNs
    odd = torch.tensor([[0.0, -0.0, 1e-45], [float("inf"), -float("inf"), float("nan")]])
    back = _decompress(_compress(odd))
    assert torch.equal(back.view(torch.int32), odd.view(torch.int32))
    # a pack written before compression (format /1: raw float32) reads the same
    old = tmp_path / "old.pt"
    torch.save({**torch.load(pack, weights_only=True), "format": "torchrl_offhrl.action_pack/1", "actions": raw.clone()}, old)
    assert torch.equal(read_action_pack(old)["actions"], raw)
    assert load_action_pack(old, workers=2, progress=False).content_hash() == small_hopper.content_hash()
