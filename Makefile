# Two entry points for a fresh machine: `make repro` and `make test`.
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

export DVC_NO_ANALYTICS := 1
export RAY_USAGE_STATS_ENABLED := 0
export MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR := false

.PHONY: install repro test dvc-deps dvc-plots clean-venv

install: $(STAMP)

# torch goes first and pinned: a satisfied range in pyproject then installs nothing more,
# whereas an unpinned resolve pulls gigabytes of CUDA wheels.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

# Stage commands call `python`: the venv's must come first on PATH. The code deps are brought up to date first, so
# a new import reruns the stages that now run it, and the charts, so that every test set of params.yaml has its own.
repro: $(STAMP) dvc-deps dvc-plots
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/dvc repro

# Three processes (pytest-xdist), a test module each at a time: a module's fixtures (a whole `dvc repro`) run once.
# One process left 30 % of the two cores idle on average (vmstat): waits for subprocesses, Ray and the disk; two
# still left room. On 2 cores the suite took 20 min 24 s in three, 24 min 06 s in two, 28 min 44 s in one (the
# last before the paper dry run rendered smaller, a minute of it); tests/conftest.py sets the order and how idle
# threads wait.
# Four took longer than three (22 min 23 s against 20 min 37 s the same day on an AVX2-only AMD VM): both cores
# are busy already.
TEST_WORKERS ?= 3
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=15

# dvc.yaml's code deps, written from what each stage imports (tools/dvc_deps.py).
dvc-deps: $(STAMP)
	$(BIN)/python -m tools.dvc_deps

# dvc.yaml's charts, written for the test sets and reconstructed sequences of params.yaml (tools/dvc_plots.py); after
# dvc-deps, which rewrites the same file.
dvc-plots: $(STAMP) dvc-deps
	$(BIN)/python -m tools.dvc_plots

clean-venv:
	rm -rf $(VENV)
