"""The README's main job, on a tiny config."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


def test_model_pipeline_tiny(tmp_path):
    env = dict(os.environ, TORCHRL_OFFHRL_CACHE=str(tmp_path / "cache"), PYTHONUNBUFFERED="1")
    out = tmp_path / "out"
    cmd = [
        sys.executable, str(ROOT / "examples" / "model_pipeline.py"),
        f"out_dir={out}", "num_transitions=1500", "dataset_num_envs=4",
        "ensemble.hidden_sizes=[32,32]", "ensemble.fit.max_steps=40",
        "cvae.hidden_sizes=[32,32]", "cvae.fit.max_steps=40",
        "rollout.batch_size=16", "rollout.steps=20", "rollout.real_envs=2", "rollout.real_steps=60",
    ]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "check_env_specs: passed" in res.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"]["transitions"] == 1500
    assert summary["rollout"]["transitions"] == 16 * 20
    # the threshold is the offline rule's (the largest held-out discrepancy), given to the env explicitly
    rules = summary["offline_rules"]
    assert summary["calibration"]["method"] == "explicit" and summary["calibration"]["threshold"] == pytest.approx(rules["threshold"])
    assert rules["evidence"]["threshold"]["held_out_max"] == pytest.approx(rules["threshold"])
    assert (out / "calibration.png").stat().st_size > 1000 and (out / "offline_rules.png").stat().st_size > 1000
    # second run: dataset and models come from the cache
    res2 = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res2.returncode == 0 and "loaded from" in res2.stdout and "collecting" not in res2.stdout
