"""No unsafe deserialisation or code execution in the package, the scripts, the examples and the benchmarks.

Fails on: ``torch.load`` without ``weights_only=True``; ``yaml.load`` / ``yaml.load_all`` without a safe loader
(``yaml.safe_load`` is fine); ``pickle.load`` / ``pickle.loads`` (also as ``cPickle``, ``dill``); the builtins ``eval``
and ``exec`` (methods named ``eval``, such as ``module.eval()``, are fine); any call with ``shell=True``.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.fault("artefact")  # issue 73's probe suite: `make probes`

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("torchrl_offhrl", "scripts", "examples", "benchmarks", "experiments")
SAFE_YAML_LOADERS = {"SafeLoader", "CSafeLoader", "BaseLoader"}


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _kw(call: ast.Call, name: str):
    return next((k.value for k in call.keywords if k.arg == name), None)


def unsafe_calls(source: str, filename: str = "<source>") -> list[str]:
    """``"file:line: what"`` for every unsafe call in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func)
        where = f"{filename}:{node.lineno}"
        if name.endswith("torch.load"):
            w = _kw(node, "weights_only")
            if not (isinstance(w, ast.Constant) and w.value is True):
                found.append(f"{where}: torch.load without weights_only=True (use torchrl_offhrl.utils.load_torch_file)")
        elif name in ("yaml.load", "yaml.load_all"):
            loader = _kw(node, "Loader") if _kw(node, "Loader") is not None else (node.args[1] if len(node.args) > 1 else None)
            if loader is None or _dotted(loader).split(".")[-1] not in SAFE_YAML_LOADERS:
                found.append(f"{where}: {name} without a safe loader (use yaml.safe_load)")
        elif name in ("yaml.unsafe_load", "yaml.full_load", "yaml.unsafe_load_all", "yaml.full_load_all"):
            found.append(f"{where}: {name} without a safe loader (use yaml.safe_load)")
        elif name.split(".")[-1] in ("load", "loads") and name.split(".")[0] in ("pickle", "cPickle", "dill", "_pickle"):
            found.append(f"{where}: {name} (unpickling runs arbitrary code)")
        elif isinstance(node.func, ast.Name) and node.func.id in ("eval", "exec"):
            found.append(f"{where}: builtin {node.func.id}()")
        shell = _kw(node, "shell")
        if isinstance(shell, ast.Constant) and shell.value is True:
            found.append(f"{where}: {name or 'a call'}(..., shell=True)")
    return found


@pytest.mark.parametrize("snippet, expect", [
    ("import torch\ntorch.load('x.pt')", "weights_only"),
    ("import torch\ntorch.load('x.pt', weights_only=False)", "weights_only"),
    ("import yaml\nyaml.load(open('a'))", "safe loader"),
    ("import yaml\nyaml.load(open('a'), Loader=yaml.FullLoader)", "safe loader"),
    ("import yaml\nyaml.unsafe_load(open('a'))", "safe loader"),
    ("import pickle\npickle.load(open('a', 'rb'))", "unpickling"),
    ("import pickle\npickle.loads(b'')", "unpickling"),
    ("eval('1 + 1')", "builtin eval"),
    ("exec('x = 1')", "builtin exec"),
    ("import subprocess\nsubprocess.run('ls', shell=True)", "shell=True"),
])
def test_the_checker_finds_each_unsafe_call(snippet, expect):
    found = unsafe_calls(snippet)
    assert len(found) == 1 and expect in found[0], found


@pytest.mark.parametrize("snippet", [
    "import torch\ntorch.load('x.pt', weights_only=True)",
    "import yaml\nyaml.safe_load(open('a'))",
    "import yaml\nyaml.load(open('a'), Loader=yaml.SafeLoader)",
    "model.eval()",
    "import subprocess\nsubprocess.run(['ls'], shell=False)",
])
def test_the_checker_passes_safe_calls(snippet):
    assert unsafe_calls(snippet) == []


def test_no_unsafe_call_in_the_repo():
    found = []
    for top in SCANNED:
        for path in sorted((ROOT / top).rglob("*.py")):
            found += unsafe_calls(path.read_text(), str(path.relative_to(ROOT)))
    assert not found, "unsafe calls:\n" + "\n".join(found)
