# Two commands do everything on a fresh machine with Python 3.11:
#   make demo   - create .venv if needed, install, run the main job on the simulated sensor
#   make test   - same set-up, then the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast bench lint clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade --quiet pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

demo: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/nodlidar demo

test: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q

test-fast: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q -m "not slow"

bench: $(STAMP)
	MPLBACKEND=Agg $(PY) benchmarks/run.py

lint: $(STAMP)
	$(VENV)/bin/ruff check nodlidar tests benchmarks notebooks

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
