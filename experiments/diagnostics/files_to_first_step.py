"""How many package files and functions does a command run before its first gradient step? (issue 71's layout measure)

    python experiments/diagnostics/files_to_first_step.py demo [KEY=VALUE ...]
    python experiments/diagnostics/files_to_first_step.py train algo=moc env=hopper dataset=medium

Runs the ``offhrl`` command with a profiler that records every function of
the package called (module and class bodies, which run on import, are not
counted), and stops the process at the first ``torch.optim.Adam.step``:
prints the count of files and functions and the files in the order they were
first entered. With cached models this takes seconds.
"""
from __future__ import annotations

import os
import sys

from torch.optim import Adam

CO_NEWLOCALS = 0x2  # set on function code objects, not on module or class bodies
files: list[str] = []
functions: set[tuple[str, str]] = set()


def _profile(frame, event, arg):
    code = frame.f_code
    if event == "call" and code.co_flags & CO_NEWLOCALS and "torchrl_offhrl" in code.co_filename and "site-packages" not in code.co_filename:
        functions.add((code.co_filename, code.co_name))
        if code.co_filename not in files:
            files.append(code.co_filename)


def _first_step(self, *args, **kwargs):
    sys.setprofile(None)
    root = os.path.commonpath(files)
    print(f"\n{len(files)} package files, {len(functions)} functions before the first Adam step:")
    for f in files:
        print("  ", os.path.relpath(f, root))
    sys.stdout.flush()
    os._exit(0)


def main() -> None:
    Adam.step = _first_step
    sys.argv = ["offhrl", *sys.argv[1:]]
    from torchrl_offhrl.cli import main as offhrl

    sys.setprofile(_profile)
    offhrl()
    sys.setprofile(None)
    print("the command ended without a gradient step")


if __name__ == "__main__":
    main()
