"""The layer contract: imports go downwards only, with no cycles and no private names across modules.

Layers, lowest first (DESIGN): the shared base modules (``utils``, ``scores``, ``stats``,
``registry``, ``nets``, ``rollouts``) < ``data`` < ``models`` < ``envs`` <
``modules`` / ``objectives`` < ``agents`` < ``recipes`` < ``cli``. Every
import counts, those inside functions too. The checker is tested on
synthetic sources, so a contract that could not fail would be caught.

Beside the package, ``experiments/`` (the results pages' drivers, not installed) imports the package's public names only,
by absolute imports, and the package imports nothing of it (the CLI's ``offhrl results`` forwards to a checkout's).
"""
from __future__ import annotations

import ast
from pathlib import Path

PKG = "torchrl_offhrl"
ROOT = Path(__file__).resolve().parents[1] / PKG
LAYERS = {
    "utils": 0, "scores": 0, "stats": 0, "registry": 0, "nets": 0, "rollouts": 0, "blockstack": 0,
    "data": 1, "models": 2, "envs": 3, "modules": 4, "objectives": 4,
    "agents": 5, "recipes": 6, "cli": 8,
}


def module_sources(root: Path = ROOT) -> dict[str, str]:
    """``{"torchrl_offhrl.data.io": source, ...}`` for every module of the package under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path.read_text()
    return out


def _is_package(name: str, modules: dict[str, str], root: Path) -> bool:
    return (root.parent / Path(*name.split(".")) / "__init__.py").is_file() or any(m.startswith(name + ".") for m in modules)


def imports_of(name: str, source: str, modules: dict[str, str], root: Path = ROOT) -> list[tuple[str, str | None, int]]:
    """``(imported module, imported name or None, line)`` for every import of the package's own modules in ``source``."""
    package = name if _is_package(name, modules, root) else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names if a.name.split(".")[0] == PKG]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != PKG:
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                out.append((sub, None, node.lineno) if sub in modules else (target, a.name, node.lineno))
    return out


def layer_of(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.get(parts[1]) if len(parts) > 1 else None  # the package root is above every layer


def violations(modules: dict[str, str], root: Path = ROOT) -> list[str]:
    """Upward imports and private names imported from another module, as readable lines."""
    bad = []
    for name, source in modules.items():
        mine = layer_of(name)
        for target, imported, line in imports_of(name, source, modules, root):
            theirs = layer_of(target)
            if mine is not None and theirs is not None and theirs > mine:
                bad.append(f"{name}:{line} imports {target} (layer {theirs}) from layer {mine}: imports must go downwards")
            if imported and imported.startswith("_") and not imported.startswith("__") and target != name:
                bad.append(f"{name}:{line} imports the private name {imported} from {target}")
    return bad


def cycles(modules: dict[str, str], root: Path = ROOT) -> list[list[str]]:
    """Import cycles between modules (strongly connected components of more than one module, or self-imports)."""
    graph = {m: {t for t, _, _ in imports_of(m, s, modules, root) if t in modules and t != m} for m, s in modules.items()}
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_every_module_has_a_layer():
    missing = sorted({m.split(".")[1] for m in module_sources() if "." in m and layer_of(m) is None})
    assert missing == [], f"give these top-level modules a layer in tests/test_layers.py and DESIGN: {missing}"


def test_imports_go_downwards_only():
    assert violations(module_sources()) == []


def test_no_import_cycles():
    assert cycles(module_sources()) == []


def _fake_package(tmp_path, files: dict[str, str]) -> Path:
    root = tmp_path / PKG
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_checker_catches_an_upward_import(tmp_path):
    """A data module reaching up into recipes (even inside a function) is reported; the same import downwards is not."""
    root = _fake_package(tmp_path, {
        "__init__.py": "",
        "data/__init__.py": "",
        "data/io.py": "def f():\n    from ..recipes.train import train\n",
        "recipes/__init__.py": "",
        "recipes/train.py": "from ..data.io import f\nfrom torchrl_offhrl.data import io\n",
    })
    mods = module_sources(root)
    (bad,) = violations(mods, root)
    assert bad.startswith("torchrl_offhrl.data.io:2 imports torchrl_offhrl.recipes.train (layer 6) from layer 1")
    assert cycles(mods, root) == [["torchrl_offhrl.data.io", "torchrl_offhrl.recipes.train"]]


def test_checker_catches_private_names_and_cycles(tmp_path):
    root = _fake_package(tmp_path, {
        "__init__.py": "",
        "data/__init__.py": "from .a import load\n",
        "data/a.py": "from .b import _helper\n\ndef load():\n    pass\n",
        "data/b.py": "from . import a\n\ndef _helper():\n    pass\n",
    })
    mods = module_sources(root)
    assert violations(mods, root) == ["torchrl_offhrl.data.a:1 imports the private name _helper from torchrl_offhrl.data.b"]
    assert cycles(mods, root) == [["torchrl_offhrl.data.a", "torchrl_offhrl.data.b"]]


def test_the_task_registry_is_the_one_place_that_knows_the_stacking_envs():
    """Code asks torchrl_offhrl.registry.task_of(env) what kind of task an env is; no id list is tested elsewhere."""
    import re

    from torchrl_offhrl.registry import TASKS, stacking_tasks, task_of

    assert {k: t.n_blocks for k, t in stacking_tasks().items()} == {"BlockStack2-v0": 2, "BlockStack3-v0": 3}
    assert not task_of("Hopper-v5").goal_conditioned and task_of("hopper") == TASKS["Hopper-v5"]
    assert not task_of(None).goal_conditioned and not task_of("Toy").goal_conditioned  # no id: no goals
    pattern = re.compile(r"BLOCKSTACK_IDS|STACKING_ENVS|\"BlockStack[23]-v0\" in |in \(\"blockstack2\"")
    offenders = [f"{path.relative_to(ROOT.parent)}:{i}" for top in (ROOT, ROOT.parent / "scripts", ROOT.parent / "benchmarks")
                 for path in sorted(top.rglob("*.py")) if path.name != "registry.py"
                 for i, line in enumerate(path.read_text().splitlines(), 1) if pattern.search(line)]
    assert not offenders, offenders


EXPERIMENTS = ROOT.parent / "experiments"


def declared_names(source: str) -> set[str] | None:
    """The names a module's ``__all__`` lists (a literal list or tuple at its top level), or None without one."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return {elt.value for elt in getattr(node.value, "elts", []) if isinstance(elt, ast.Constant)}
    return None


def experiment_violations(root: Path = EXPERIMENTS, package: Path = ROOT) -> list[str]:
    """The experiments' imports of the package that are relative, of a module that does not exist, of a private name, or of
    a name its module does not declare public (not in its ``__all__``, where it has one; a submodule is public)."""
    modules = module_sources(package)
    bad = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level and path.parent == root:
                bad.append(f"{path.name}:{node.lineno} imports relatively from the top of experiments/")
            names = ([(a.name, None) for a in node.names] if isinstance(node, ast.Import) else
                     [(node.module or "", a.name) for a in node.names] if isinstance(node, ast.ImportFrom) and not node.level else [])
            for module, name in names:
                if module.split(".")[0] != PKG:
                    continue
                if module not in modules:
                    bad.append(f"{path.relative_to(root)}:{node.lineno} imports {module}, not a module of {PKG}")
                if (name or "").startswith("_") or any(part.startswith("_") for part in module.split(".")):
                    bad.append(f"{path.relative_to(root)}:{node.lineno} imports a private name: {module} {name or ''}".rstrip())
                elif name and name != "*" and module in modules and f"{module}.{name}" not in modules:
                    public = declared_names(modules[module])
                    if public is not None and name not in public:
                        bad.append(f"{path.relative_to(root)}:{node.lineno} imports {module} {name}, not in that module's __all__")
    return bad


def test_the_experiments_stand_beside_the_package():
    """experiments/ imports the package by absolute, public names; no module of the package imports experiments (the CLI's
    forwarder does so by name at run time, from a checkout); the wheel holds none of it (pyproject's package list)."""
    assert experiment_violations() == []
    offenders = [m for m, src in module_sources().items() for node in ast.walk(ast.parse(src))
                 if isinstance(node, (ast.Import, ast.ImportFrom)) and m != f"{PKG}.cli"
                 and any((a.name if isinstance(node, ast.Import) else node.module or "").startswith("experiments") for a in node.names)]
    assert offenders == []
    assert 'include = ["torchrl_offhrl*"]' in (ROOT.parent / "pyproject.toml").read_text()


def test_the_experiments_checker_catches_relative_and_private_imports(tmp_path):
    pkg = _fake_package(tmp_path, {"__init__.py": "", "data/__init__.py": "", "data/io.py": "def load():\n    pass\n"})
    exp = tmp_path / "experiments"
    exp.mkdir()
    (pkg / "data" / "api.py").write_text('__all__ = ["load"]\nfrom .io import load, load as helper\n')
    (exp / "run.py").write_text("from torchrl_offhrl.data.io import load\nfrom torchrl_offhrl.data.io import _x\n"
                                "from torchrl_offhrl.nothing import y\nfrom . import z\n"
                                "from torchrl_offhrl.data.api import load, helper\nfrom torchrl_offhrl.data import io\n")
    assert experiment_violations(exp, pkg) == ["run.py:2 imports a private name: torchrl_offhrl.data.io _x",
                                               "run.py:3 imports torchrl_offhrl.nothing, not a module of torchrl_offhrl",
                                               "run.py:4 imports relatively from the top of experiments/",
                                               "run.py:5 imports torchrl_offhrl.data.api helper, not in that module's __all__"]
