# Everything a fresh clone needs: `make test` and `make train` set up .venv themselves.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup test test-all train evaluate bench lint clean

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

test-all: $(STAMP)
	$(PY) -m pytest -m ''

train: $(STAMP)
	$(PY) train.py

evaluate: $(STAMP)
	$(PY) evaluate.py task=synthesis

bench: $(STAMP)
	for b in bench/*.py; do $(PY) $$b || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
