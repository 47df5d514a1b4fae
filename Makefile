# FisheyeDepth: the two commands of the README are `make train` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# A GPU user installs a CUDA build of torch 2.13.0 into the venv first (see README); the
# constraints file then accepts it (torch==2.13.0 matches any 2.13.0+<build> wheel).
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed

.PHONY: install test lint bench train reproduce realscore clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -c constraints.txt "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,export,viz]"
	touch $(STAMP)

# One pytest-xdist worker per core, each test file on one worker (its module fixtures built once).
TEST_WORKERS ?= auto
test: install
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

lint: install
	$(PY) -m ruff check --no-cache src tests scripts train.py eval.py predict.py export.py
	$(PY) -m ruff format --no-cache --check src tests scripts train.py eval.py predict.py export.py

# The CPU benchmarks that need no trained checkpoint; each writes its section of BENCHMARKS.md.
# ARGS=--quick: the smallest sizes, to check that they run (nothing written). scripts/bench/: the rest.
bench: install
	$(PY) scripts/bench/bench_geometry.py $(ARGS)
	$(PY) scripts/bench/bench_synthetic.py $(ARGS)
	$(PY) scripts/bench/bench_training.py $(ARGS)
	$(PY) scripts/bench/bench_inference.py $(ARGS)

# The main job: render the default synthetic dataset if missing, train the full model (CPU budget),
# evaluate it on the test split, print the metric table, write colourised distance maps.
train: install
	$(PY) train.py $(ARGS)

# Tables 1 and 2 on the synthetic world at a CPU budget; results into BENCHMARKS.md.
reproduce: install
	$(PY) scripts/research/reproduce.py $(ARGS)

# A checkpoint (or an exported .onnx) scored on every real frame with ground truth (FISHEYEDEPTH_REALDATA,
# default ../shared/realdata) beside a constant map: make realscore CKPT=RUN/checkpoints/last.ckpt
# [ARGS="--pictures out/ --json out/real.json"].
FISHEYEDEPTH_REALDATA ?= $(abspath ../shared/realdata)
realscore: install
	@test -n "$(CKPT)" || { echo "usage: make realscore CKPT=FILE.ckpt|FILE.onnx [ARGS=...]" >&2; exit 2; }
	FISHEYEDEPTH_REALDATA="$(FISHEYEDEPTH_REALDATA)" $(PY) scripts/tools/real_world.py $(CKPT) $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache src/*.egg-info
