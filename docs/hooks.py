"""MkDocs hooks: the configuration reference and the API reference are generated from the repository at build time.

Nothing generated is committed: ``configuration.md`` is the shipped YAML files (their comments are the documentation
of each key), and each API page is one ``::: package`` directive that mkdocstrings fills from the docstrings.
"""
from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "torchrl_offhrl" / "configs"

#: API pages: title -> the package mkdocstrings documents (in the order of the import layers, lowest first)
API = {
    "data": "torchrl_offhrl.data", "models": "torchrl_offhrl.models", "envs": "torchrl_offhrl.envs",
    "modules": "torchrl_offhrl.modules", "objectives": "torchrl_offhrl.objectives", "agents": "torchrl_offhrl.agents",
    "recipes": "torchrl_offhrl.recipes", "blockstack": "torchrl_offhrl.blockstack", "stats": "torchrl_offhrl.stats",
    "scores": "torchrl_offhrl.scores", "registry": "torchrl_offhrl.registry",
}


def configuration_page() -> str:
    out = ["# Configuration reference", "",
           "Every shipped [Hydra](https://hydra.cc) config, as the package holds it (`torchrl_offhrl/configs/`, also "
           "reachable as `configs/` in a clone). The comments are the documentation of each key; a command takes any "
           "of them as an override (`offhrl train algo=moc train.total_frames=81920`), and "
           "`torchrl_offhrl.recipes.schema.validate_config` checks every value before any work starts.", ""]
    groups = [("Top-level configs", sorted(CONFIGS.glob("*.yaml")))]
    groups += [(f"`{d.name}` group", sorted(d.glob("*.yaml"))) for d in sorted(p for p in CONFIGS.iterdir() if p.is_dir())]
    for title, files in groups:
        if not files:
            continue
        out += [f"## {title}", ""]
        for f in files:
            out += [f"### `{f.relative_to(CONFIGS)}`", "", "```yaml", f.read_text().rstrip(), "```", ""]
    return "\n".join(out)


def api_page(title: str, module: str) -> str:
    return f"# `{module}`\n\n::: {module}\n"


def on_files(files, config):
    files.append(File.generated(config, "reference/configuration.md", content=configuration_page()))
    for title, module in API.items():
        files.append(File.generated(config, f"reference/api/{title}.md", content=api_page(title, module)))
    return files
