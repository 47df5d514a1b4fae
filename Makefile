# FisheyeDepth: the two commands of the README are `make train` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# A GPU user installs a CUDA build of torch 2.13.0 into the venv first (see README); the
# constraints file then accepts it (torch==2.13.0 matches any 2.13.0+<build> wheel).
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed

.PHONY: install test lint bench train clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -c constraints.txt "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev]"
	touch $(STAMP)

test: install
	$(PY) -m pytest

lint: install
	$(PY) -m ruff check --no-cache src tests scripts
	$(PY) -m ruff format --no-cache --check src tests scripts

bench: install
	$(PY) scripts/bench_geometry.py
	$(PY) scripts/bench_synthetic.py
	$(PY) scripts/bench_training.py

train: install
	@echo "make train: the training entry point (train.py, Hydra configs, synthetic default data) is wired by" >&2
	@echo "the Experiments issue (#6) and is not available yet. The geometry core is: see README.md." >&2
	@exit 2

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache src/*.egg-info
