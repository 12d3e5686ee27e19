"""``offhrl results``: one command for every page under docs/results/ (issue 40).

Every page names the command that makes it (or says it is a hand-written or
frozen record), every such command names a preset that exists and a
sub-command that preset accepts, and ``offhrl results rebuild`` remakes the
committed pages byte for byte from the committed archives.
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_offhrl.cli import main
from experiments.results import PRESETS

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
GUIDE = ROOT / "docs" / "guides" / "offline.md"
#: what a page must say about where it comes from: a command that makes it, or that no command does
MARKERS = ("offhrl results ", "offhrl tune ", "Not rebuilt by any command", "Hand-written record")


def pages() -> list[Path]:
    """The markdown pages under docs/results/, archived run folders (``runs/``) aside."""
    return sorted(p for p in RESULTS.rglob("*.md") if "runs" not in p.relative_to(RESULTS).parts[:-1]
                  and not p.relative_to(RESULTS).parts[0].endswith("_runs"))


def test_every_results_page_says_what_makes_it():
    missing = [str(p.relative_to(ROOT)) for p in pages() if not any(m in p.read_text() for m in MARKERS)]
    assert pages() and not missing, f"pages that name no command and are not marked as records: {missing}"


def _commands(text: str) -> list[list[str]]:
    out = []
    for m in re.finditer(r"`(offhrl results [^`]+)`", text):
        words = [w for w in m.group(1).split() if w != "..."]
        out.append(words[2:])
    return out


def test_every_results_command_on_a_page_names_a_preset_and_a_subcommand_it_accepts(capsys):
    seen = set()
    for p in [*pages(), ROOT / "README.md", *sorted((ROOT / "docs" / "guides").glob("*.md"))]:
        for words in _commands(p.read_text()):
            assert words, f"{p}: a bare `offhrl results`"
            if words[0] in ("list", "rebuild"):
                continue
            assert words[0] in PRESETS, f"{p.relative_to(ROOT)}: unknown preset {words[0]!r} in `offhrl results {' '.join(words)}`"
            if len(words) > 1 and not words[1].startswith("-") and "/" not in words[1]:
                seen.add((words[0], words[1]))
    assert ("table1", "report") in seen and ("robustness", "table") in seen
    for preset, sub in sorted(seen):
        with pytest.raises(SystemExit) as e:  # --help after the sub-command: argparse exits 0 where the sub-command exists
            PRESETS[preset].main([sub, "--help"])
        assert e.value.code == 0, f"offhrl results {preset} {sub}: not a command of the preset"
    capsys.readouterr()


def test_list_and_unknown_preset(capsys):
    assert main(["results", "list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in PRESETS)
    assert main(["results", "tabel1", "report"]) == 2
    err = capsys.readouterr().err
    assert "unknown results preset 'tabel1'" in err and "table1" in err
    assert main(["results", "rebuild", "nope"]) == 2
    assert "unknown preset(s) ['nope']" in capsys.readouterr().err


def test_a_folder_that_is_no_checkout_is_refused(tmp_path):
    from experiments.results.paths import require_checkout

    with pytest.raises(FileNotFoundError, match="run it from the repository root"):
        require_checkout(tmp_path)
    (tmp_path / "docs" / "results").mkdir(parents=True)
    assert require_checkout(tmp_path) == tmp_path


def test_rebuild_remakes_the_committed_pages_exactly(tmp_path):
    """The committed archives give back the committed pages (in a copy of docs/results/, via $TORCHRL_OFFHRL_ROOT)."""
    shutil.copytree(RESULTS, tmp_path / "docs" / "results")
    (tmp_path / "docs" / "guides").mkdir()
    shutil.copyfile(GUIDE, tmp_path / "docs" / "guides" / "offline.md")  # Table I's report rewrites its summary there
    env = {**os.environ, "TORCHRL_OFFHRL_ROOT": str(tmp_path), "MPLBACKEND": "Agg"}
    res = subprocess.run([sys.executable, "-m", "torchrl_offhrl.cli", "results", "rebuild"], env=env, capture_output=True, text=True,
                         cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    rebuilt = [line.split("rebuilt: ", 1)[1] for line in res.stdout.splitlines() if line.startswith("rebuilt: ")]
    assert len(rebuilt) == sum(len(p.rebuild) for p in PRESETS.values())
    changed = [str(p.relative_to(tmp_path)) for p in [*sorted((tmp_path / "docs" / "results").rglob("*.md")), tmp_path / "docs" / "guides" / "offline.md"]
               if p.read_text() != (ROOT / p.relative_to(tmp_path)).read_text()]
    assert not changed, f"pages the rebuild changed: {changed} (rerun `offhrl results rebuild` and commit)"
    assert all(shlex.split(c)[2] in PRESETS for c in rebuilt)


def test_the_guides_summary_is_the_pages_table(tmp_path):
    """The offline guide's summary block is what table1's report writes from the pages' table.csv: hand-made csvs give a
    hand-written block (IQM [CI] (seeds), empty where no run, the behaviour row), and the committed guide holds the block of
    the committed csvs."""
    from experiments.results.table1 import GUIDE_BEGIN, GUIDE_END, guide_summary, write_guide_summary

    head = "env,dataset,algo,seeds,score_iqm,score_ci,selected_iqm,selected_ci,behaviour_score\n"
    for scale, rows in {"demo": ["Hopper-v5,medium,moc,5,55.14,\"(28.41, 84.56)\",34.46,\"(34.36, 34.57)\",35.89"],
                        "full": ["Hopper-v5,medium-expert,td3bc,5,91.3,\"(57.8, 102.04)\",,,53.17",
                                 "Hopper-v5,medium-expert,bc,5,57.0,\"(33.4, 93.1)\",,,53.08",
                                 "HalfCheetah-v5,medium,cql,3,38.77,\"(24.59, 46.17)\",,,38.04",
                                 "HalfCheetah-v5,medium,iql,1,44.93,\"(44.93, 44.93)\",,,38.04"]}.items():
        (tmp_path / "docs" / "results" / scale).mkdir(parents=True)
        (tmp_path / "docs" / "results" / scale / "table.csv").write_text(head + "\n".join(rows) + "\n")
    lines = guide_summary(tmp_path).splitlines()
    assert lines[0] == GUIDE_BEGIN and lines[-1] == GUIDE_END
    assert lines[2] == ("| final evaluation, IQM [95% CI] (seeds) | hopper-medium, demo | hopper-medium, full | hopper-medium-expert, demo "
                        "| hopper-medium-expert, full | halfcheetah-medium, demo | halfcheetah-medium, full | halfcheetah-medium-expert, demo "
                        "| halfcheetah-medium-expert, full |")
    assert lines[4:-2] == ["| MOC (the default): the policy it returns | 34.5 [34.4, 34.6] (5) |  |  |  |  |  |  |  |",  # the guard's choice
                           "| MOC (the default): its last policy | 55.1 [28.4, 84.6] (5) |  |  |  |  |  |  |  |",
                           "| IQL |  |  |  |  |  | 44.9 (1) |  |  |",  # one seed: no interval, as on the table page
                           "| CQL |  |  |  |  |  | 38.8 [24.6, 46.2] (3) |  |  |",
                           "| TD3+BC |  |  |  | 91.3 [57.8, 102.0] (5) |  |  |  |  |",
                           "| BC |  |  |  | 57.0 [33.4, 93.1] (5) |  |  |  |  |",
                           "| behaviour data | 35.9 |  |  | 53.2 |  | 38.0 |  |  |"]  # the first run's behaviour score of a column
    guide = tmp_path / "docs" / "guides" / "offline.md"
    assert write_guide_summary(tmp_path) is False  # no guide here: nothing to keep in step
    guide.parent.mkdir(parents=True)
    guide.write_text("# Offline\n\nno block\n")
    with pytest.raises(SystemExit, match="summary block"):
        write_guide_summary(tmp_path)
    guide.write_text(f"before\n{GUIDE_BEGIN}\nstale\n{GUIDE_END}\nafter\n")
    assert write_guide_summary(tmp_path) is True and write_guide_summary(tmp_path) is False
    assert guide.read_text() == "before\n" + guide_summary(tmp_path) + "\nafter\n"
    text = GUIDE.read_text()  # the committed guide: its block is the committed pages'
    assert text[text.index(GUIDE_BEGIN):text.index(GUIDE_END) + len(GUIDE_END)] == guide_summary(ROOT)


def test_a_run_on_the_paper_settings_gets_its_own_column_beside_the_default():
    """Table I's headline model-env columns hold the shipped default only: a run whose latent origin is the paper's (``zero``,
    preset=paper) or absent (made before the offline rules) goes to ``<label>_paper``; dataset agents use no model and stay."""
    from torchrl_offhrl.recipes.report import column_title, table_column

    def run(algo, model_env=None, label=None, **algo_keys):
        cfg = {"algo": {"name": algo, **({"label": label} if label else {}), **algo_keys}, "env": {"env_id": "Hopper-v5"},
               "dataset": "medium", "seed": 4}
        return {"config": {**cfg, **({"model_env": model_env} if model_env is not None else {})}}

    assert table_column(run("moc", {"latent_origin": "best"})) == "moc"
    assert table_column(run("moc", {"latent_origin": "behaviour"})) == "moc"
    assert table_column(run("moc", {"latent_origin": "zero"})) == "moc_paper"
    assert table_column(run("moc")) == "moc_paper"  # before the rules: no latent origin in the config
    assert table_column(run("moc", {"latent_origin": "zero"}, label="moc_1opt")) == "moc_1opt_paper"
    assert table_column(run("iql")) == "iql" and table_column(run("bc", {"latent_origin": "zero"})) == "bc"
    assert table_column(run("ppo", {"latent_origin": "zero"}, label="morel", bc_init_steps=10)) == "morel_paper"
    assert table_column(run("ppo", None, label="morel")) == "morel_style"  # the old MOReL-style config stays apart
    assert column_title("moc_paper") == "MOC (paper preset)" and column_title("moc_1opt_paper") == "MOC, 1 option (paper preset)"
    assert column_title("moc") == "MOC"
    stacking = run("uof", {"latent_origin": "zero"})
    stacking["config"]["env"] = {"env_id": "BlockStack2-v0"}
    assert table_column(stacking) == "uof"  # block stacking ships the paper's setting: no preset column


def test_offhrl_results_outside_a_checkout_says_where_the_experiments_are(tmp_path, monkeypatch):
    """An installed (non-editable) library has no experiments: `offhrl results` refuses in one message naming what to do."""
    from torchrl_offhrl import cli

    monkeypatch.setattr(cli, "__file__", str(tmp_path / "site-packages" / "torchrl_offhrl" / "cli.py"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("TORCHRL_OFFHRL_ROOT", raising=False)
    with pytest.raises(SystemExit, match="not installed with the library.*run it from the repository root"):
        cli.cmd_results(type("Args", (), {"args": ["list"]})())
    assert cli.checkout_root() == tmp_path


def test_the_options_section_pairs_the_algorithms_seed_by_seed():
    """MOC, 1-option MOC and PPO on two shared seeds (and a 1-option seed MOC lacks): per-seed differences by hand."""
    from experiments.results.table1 import _options_section

    def run(name, final, returned):
        return {"name": name, "summary": {"final": {"normalized_d4rl": final}, "selected": {"normalized_d4rl": returned}}}

    rows = _options_section([run("moc-hopper-medium-seed4", 10.0, 30.0), run("moc-hopper-medium-seed5", 20.0, 30.0),
                             run("moc_1opt-hopper-medium-seed4", 12.0, 30.0), run("moc_1opt-hopper-medium-seed5", 25.0, 31.0),
                             run("moc_1opt-hopper-medium-seed6", 90.0, 30.0), run("ppo-hopper-medium-seed4", 10.0, 30.0),
                             run("iql-hopper-medium-seed4", 50.0, 50.0)])
    one = rows[-1]
    assert one.startswith("| hopper-medium | 1 option - MOC | 2 | +3.5 [") and "(+2.0, +5.0)" in one and one.endswith("(+0.0, +1.0) |")
    assert len(rows) == 8  # title, text, head, one row (and their blank lines): no PPO row (one shared seed is no pair)
    assert _options_section([run("iql-hopper-medium-seed4", 50.0, 50.0)]) == []


def test_the_guard_section_counts_right_and_wrong_decisions_by_hand():
    """Four hand-made runs: fired and right, fired and wrong (cost 10), passed and right, passed and wrong (cost 5); a run
    without a guard (a dataset agent) is left out."""
    from experiments.results.table1 import _guard_section

    def run(name, fired, start, last):
        ev = [{"frames": 0, "normalized_d4rl": start}, {"frames": 100, "normalized_d4rl": last}]
        guard = None if fired is None else {"fired": fired, "candidate_step": 100}
        return {"name": name, "evals": ev, "summary": {"guard": guard}}

    rows = _guard_section([run("moc-hopper-medium-seed4", True, 30.0, 25.0), run("moc-hopper-medium-seed5", True, 30.0, 40.0),
                           run("moc-hopper-medium-seed6", False, 30.0, 50.0), run("moc-hopper-medium-seed7", False, 30.0, 25.0),
                           run("iql-hopper-medium-seed4", None, 30.0, 60.0)])
    assert rows[-1] == "| hopper-medium | moc | 4 | 2 | 1 | 10.0 | 2 | 1 | 5.0 |" and len(rows) == 8  # title, text, head, one row
    assert _guard_section([run("iql-hopper-medium-seed4", None, 30.0, 60.0)]) == []
