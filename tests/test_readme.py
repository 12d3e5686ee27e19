"""The README's code block runs as written (with smaller sizes)."""
import re
from pathlib import Path


def test_readme_snippet(tmp_path, monkeypatch):
    text = (Path(__file__).parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 2, "the README has two python blocks: models + env, then options"
    block = blocks[0]
    small = {
        "20_000": "2_000",
        "max_steps=500": "max_steps=5",
        "DynamicsEnsemble.for_dataset(data, num_models=5)": "DynamicsEnsemble.for_dataset(data, num_models=5, hidden_sizes=(32, 32))",
        "ConditionalVAE.for_dataset(data)": "ConditionalVAE.for_dataset(data, hidden_sizes=(32, 32))",
        "batch_size=[1024]": "batch_size=[8]",
        "env.rollout(1000,": "env.rollout(20,",
    }
    for old, new in small.items():
        assert old in block, old  # the README still says what this test shrinks
        block = block.replace(old, new)
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert scope["rollout"].batch_size == (8, 20)
    assert len(scope["rb"]) == len(scope["data"]) and scope["rb"].sample().batch_size == (256,)
    options = blocks[1]
    for old, new in {"1024 * 16 * 10": "8 * 16 * 2", "1024 * 16": "8 * 16"}.items():
        assert old in options, old
        options = options.replace(old, new)
    exec(compile(options, "README.md (options)", "exec"), scope)
    batch = scope["batch"]
    assert batch.batch_size == (8, 16)
    assert {"option", "prev_option", "termination_prob", "option_log_probs", "latent_action", "action"} <= set(batch.keys())
    assert (batch["next", "prev_option"] == batch["option"]).all()
    assert (tmp_path / "calibration.png").is_file() and (tmp_path / "hopper_random.hdf5").is_file()
