# Everything a fresh clone needs: `make test` and `make train` set up .venv themselves.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup test test-slow test-all ci train evaluate bench lint clean

setup: $(STAMP)

# Rebuilt when missing or older than pyproject.toml or requirements-nodeps.txt (pinned wheels whose declared
# requirements clash with ours: installed without resolving, see that file).
$(STAMP): pyproject.toml requirements-nodeps.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[dev]'
	$(PY) -m pip install --no-deps -r requirements-nodeps.txt
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest

test-slow: $(STAMP)
	$(PY) -m pytest -m slow

test-all: $(STAMP)
	$(PY) -m pytest -m ''

# What .ci/run runs: the fast tier, the slow tier (training resume/export/DDP, SLAM end to end, the entry points
# in subprocesses), then ruff.
ci: test test-slow lint

train: $(STAMP)
	$(PY) train.py

evaluate: $(STAMP)
	$(PY) evaluate.py task=synthesis

# The benchmarks that run with their defaults. The others take what they measure as an argument:
# keypoint_shift.py IMAGE, scale_drift.py VARIANT, part_swap.py task=matching ..., rgbd_matches.py TUM_FOLDER,
# ba_regression.py DATA_ROOT; fine_cells_device.sh is the GPU training run (docs/finer_cells.md).
BENCHES := synthetic_sequence procedural synthesis teachers extractor student_profile bad_inputs slam \
	bundle_adjustment triangulation_matching

bench: $(STAMP)
	for b in $(BENCHES); do $(PY) bench/$$b.py || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
