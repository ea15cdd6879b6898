# Two commands do everything on a fresh machine with Python 3.11:
#   make demo   - create .venv if needed, install, run the main job on the simulated sensor
#   make test   - same set-up, then the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast bench lint clean venv constraints

venv: $(STAMP)

# Open3D (the independent PLY/PCD reader of the tests) loads libusb-1.0 at import; a fresh
# Debian machine lacks it. Installed through the system's package manager when we may.
SYSLIBS := libusb-1.0-0

# constraints.txt pins every package to the versions the suite last passed with (see its
# header); pyproject.toml keeps loose lower bounds for library users.
$(STAMP): pyproject.toml constraints.txt
	@ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || { \
	  command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] && \
	  { apt-get install -y -qq $(SYSLIBS) >/dev/null 2>&1 || \
	    { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq $(SYSLIBS) >/dev/null 2>&1; }; } ; } || \
	  echo "note: $(SYSLIBS) not installed; the Open3D reader tests will skip"
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade --quiet pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev]'
	@touch $(STAMP)

demo: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/nodlidar demo

test: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q

# everything but the tests marked slow (tests/conftest.py lists the end-to-end ones): under a
# minute on a 2-core machine (~28 s of CPU); `make test` runs them all. With pytest-xdist (a
# dev dependency) installed, two workers take whole files each (module fixtures computed
# once per file): about a third less wall time.
XDIST_ARGS := -n 2 --dist loadfile
test-fast: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q -m "not slow" \
	  $$($(PY) -c 'import xdist' 2>/dev/null && printf '%s' '$(XDIST_ARGS)')

# every benchmark in a fresh process, the whole set three times: min/median of every figure
# (ratios against baselines of the same run, peak RSS) in out/bench.json
bench: $(STAMP)
	MPLBACKEND=Agg $(PY) benchmarks/run.py --repeat 3 --json out/bench.json

# ruff, then the type check of the package (mypy; settings in pyproject.toml [tool.mypy])
lint: $(STAMP)
	$(VENV)/bin/ruff check nodlidar tests benchmarks notebooks
	$(PY) -m mypy

# after upgrading packages in .venv and a passing `make test`: pin what is installed now
constraints: $(STAMP)
	@{ sed -n '/^#/p' constraints.txt; $(PY) -m pip freeze --all --exclude-editable | grep -v '^pip=='; } > constraints.txt.new
	@mv constraints.txt.new constraints.txt && echo "constraints.txt: $$(grep -vc '^#' constraints.txt) pins"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
	find nodlidar -name '*.nb[ic]' -delete  # numba's kernel caches (nodlidar/_compiled_geometry.py)
