# The README's two commands: `make demo` (main job) and `make test`; `make docs` builds the docs site.
# Both create .venv and install everything on a fresh machine.
# torch goes in first so that pip does not pull a multi-GB CUDA build:
#   make test TORCH_VERSION=2.13.0                      (CPU build, default)
#   make test TORCH_SPEC="torch" TORCH_INDEX=https://download.pytorch.org/whl/cu126   (GPU)
PYTHON ?= python3
VENV ?= .venv
TORCH_VERSION ?= 2.13.0
TORCH_SPEC ?= torch==$(TORCH_VERSION)
TORCH_INDEX ?=
PY := $(VENV)/bin/python
# pytest-xdist workers for `make test`, one torch thread each (tests/conftest.py); TEST_WORKERS=0 runs one process
TEST_WORKERS ?= 2

.PHONY: install demo test probes docs bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH_SPEC)" $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(PY) -m pip install --quiet -e ".[test]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/offhrl demo

test: install
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile

# issue 73's probe suite (also part of `make test`): each fault class's tests, counted per class at the end
probes: install
	$(PY) -m pytest -m fault -p no:cacheprovider -q

docs: install
	$(PY) -m pip install --quiet -e ".[docs]"
	$(VENV)/bin/mkdocs build --strict

bench: install
	$(PY) benchmarks/ensemble_training.py
	$(PY) benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) outputs .pytest_cache build/site
