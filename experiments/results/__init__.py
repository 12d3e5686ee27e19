"""Every results page under ``docs/results/``, run and rebuilt by one command: ``offhrl results PRESET ...``.

A *preset* is one experiment family: its runs (resumable run directories
under ``outputs/``, each archived into ``docs/results/`` as it finishes, so
the pages grow across machines and sessions) and its report (the pages,
rebuilt from the archive). ``offhrl results list`` names them and the pages
each writes; ``offhrl results PRESET --help`` gives a preset's own commands;
``offhrl results rebuild`` remakes every page that its archive alone can
make, and says what the others need.

The presets (``offhrl results list`` prints the pages each writes):

- ``table1``: the paper's Table I, every algorithm on hopper / halfcheetah x medium / medium-expert, demo and full scale;
- ``transfer``: offline training, then online fine-tuning on the backward task;
- ``blockstack``: goal-conditioned block stacking (UOF, SAC+HER, BC and the ablations);
- ``tune``: the paper's model search on Ray Tune;
- ``uof-online``: UOF trained online (the paper's route to its block-stacking data);
- ``robustness``: the demo setting on many dataset seeds;
- ``moc-experiments``, ``option-check``, ``blockstack-fidelity``: MOC's development variants, whether its options
  differ, the stacking env against the paper's.

The modules hold each preset's logic (``experiments.results.table1`` ...);
where the pages and runs live: :mod:`experiments.results.paths`.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

__all__ = ["PRESETS", "Preset", "main", "rebuild"]


@dataclass(frozen=True)
class Preset:
    """One experiment family: the module with its ``main(argv)``, what it is, the pages it writes (under
    ``docs/results/``), the reports its archive alone rebuilds, and what the other pages need."""

    module: str
    what: str
    pages: tuple[str, ...]
    rebuild: tuple[tuple[str, ...], ...] = ()
    needs: str = ""

    def main(self, argv: list[str]) -> int:
        rc = importlib.import_module(f"{__name__}.{self.module}").main(list(argv))
        return 0 if rc is None else int(rc)


PRESETS: dict[str, Preset] = {
    "table1": Preset("table1", "the paper's Table I: every algorithm on hopper / halfcheetah x medium / medium-expert, demo and full scale",
                     ("demo/", "full/", "demo_tuning/", "full_tuning/"),
                     (("report", "--scale", "demo"), ("report", "--scale", "full"), ("report", "--scale", "demo", "--tuning"),
                      ("report", "--scale", "full", "--tuning"))),
    "transfer": Preset("transfer", "offline training on the forward task, then online fine-tuning on the backward task",
                       ("transfer.md", "transfer/", "transfer_tuning.md", "transfer_sampled.md"),
                       (("report",), ("report", "--tuning")),
                       "transfer_sampled.md evaluates the runs' final checkpoints (outputs/results/transfer/): `offhrl results transfer sampled`"),
    "blockstack": Preset("blockstack", "goal-conditioned block stacking: UOF, SAC+HER and BC, with the ablations",
                         ("block_stacking.md", "blockstack/"), (("report",),)),
    "tune": Preset("tune", "the paper's model search (ensemble and CVAE widths, learning rates) on Ray Tune", ("tune.md", "tune/"), (("report",),)),
    "uof-online": Preset("uof_online", "UOF trained online in the real env, the paper's route to its block-stacking data",
                         ("uof_online/",), (("report",),)),
    "robustness": Preset("robustness", "the demo setting on many dataset seeds (does the method work on any machine)",
                         ("demo_robustness.md",), (("table",),)),
    "moc-experiments": Preset("moc_experiments", "MOC's development variants at the demo scale", ("moc_demo_experiments.md",),
                              needs="its run directories (outputs/moc_experiments/): `offhrl results moc-experiments table`"),
    "option-check": Preset("option_check", "whether MOC's options differ (KL between intra-option policies, where each is active)",
                           ("demo/option_check.md", "full/option_check.md"),
                           needs="the runs' checkpoints (outputs/results/<scale>/moc-*): the command on each page"),
    "blockstack-fidelity": Preset("blockstack_fidelity", "the stacking env and its datasets against the paper's",
                                  ("blockstack/fidelity.md",), needs="regenerates the datasets: `offhrl results blockstack-fidelity`"),
}


def listing() -> str:
    """The presets, a line each: name, pages, what."""
    width = max(map(len, PRESETS))
    return "\n".join(f"{name:<{width}}  {p.what}\n{'':<{width}}  pages: {', '.join('docs/results/' + x for x in p.pages)}"
                     for name, p in PRESETS.items())


def rebuild(names: list[str] | None = None) -> list[str]:
    """Remake every page an archive alone can make (each preset's ``rebuild`` reports); the lines it printed."""
    from .paths import require_checkout

    require_checkout()
    unknown = sorted(set(names or ()) - set(PRESETS))
    if unknown:
        raise ValueError(f"unknown preset(s) {unknown}; the presets: {', '.join(PRESETS)}")
    lines = []
    for name, p in PRESETS.items():
        if names and name not in names:
            continue
        for argv in p.rebuild:
            print(f"== offhrl results {name} {' '.join(argv)}", flush=True)
            p.main(list(argv))
            lines.append(f"rebuilt: offhrl results {name} {' '.join(argv)}")
        if p.needs:
            lines.append(f"not rebuilt from the archive ({name}): {p.needs}")
    print("\n".join(lines))
    return lines


def main(argv: list[str]) -> int:
    """``offhrl results``: ``list``, ``rebuild [PRESET ...]`` or ``PRESET ARGS...`` (the preset's own command line)."""
    argv = list(argv)
    if not argv or argv[0] in ("-h", "--help", "list"):
        print("offhrl results PRESET ARGS...   (offhrl results PRESET --help: the preset's commands)\n"
              "offhrl results rebuild [PRESET ...]   every page its archive alone rebuilds\n\n" + listing())
        return 0
    if argv[0] == "rebuild":
        rebuild(argv[1:])
        return 0
    if argv[0] not in PRESETS:
        raise ValueError(f"unknown results preset {argv[0]!r}; the presets: {', '.join(PRESETS)} (offhrl results list)")
    if not any(a in ("-h", "--help") for a in argv[1:]):
        from .paths import require_checkout

        require_checkout()
    return PRESETS[argv[0]].main(argv[1:])
