"""``python -m experiments.results ARGS`` from the repository root: the same as ``offhrl results ARGS``."""
import sys

from experiments.results import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
