# layerwatch — the two commands a user needs are `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
STAMP := $(VENV)/.installed-stamp
OUT ?= demo-out

.PHONY: demo test check bench lint types install clean

$(STAMP): pyproject.toml setup.py src/layerwatch/gcode/_ckernel.c
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[web,notify,dask,mqtt,fast,test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/layerwatch demo --out $(OUT)

# Tests run on two pytest-xdist workers (`--dist loadgroup`; every real-server test is in xdist_group
# "servers", tests on wall-clock time are `exclusive`): ~10-12 instead of ~17 min on the 2-core machine.
# `make test PYTEST_WORKERS=0` runs them in one process (e.g. with --pdb). See README.
PYTEST_WORKERS ?= 2
XDIST := $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist loadgroup)

test: $(STAMP)
	$(PY) -m pytest $(XDIST) --durations=20

# Fast feedback (issue 17): lint + types + every test not marked `slow`.
check: lint types
	$(PY) -m pytest $(XDIST) -m "not slow" -q

bench: $(STAMP)
	$(PY) -m pytest benchmarks -p no:cacheprovider -s -o python_files="bench_*.py"
	$(PY) benchmarks/farm_capacity.py --quick

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

types: $(STAMP)
	$(VENV)/bin/mypy src/layerwatch

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .benchmarks .layerwatch-cache
