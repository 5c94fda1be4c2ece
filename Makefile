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
	$(PY) -m pip install --quiet -e '.[web,notify,dask,mqtt,test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/layerwatch demo --out $(OUT)

test: $(STAMP)
	$(PY) -m pytest --durations=20

# Fast feedback (issue 17): lint + types + every test not marked `slow`.
check: lint types
	$(PY) -m pytest -m "not slow" -q

bench: $(STAMP)
	$(PY) -m pytest benchmarks -p no:cacheprovider -s -o python_files="bench_*.py"
	$(PY) benchmarks/farm_capacity.py --quick

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

types: $(STAMP)
	$(VENV)/bin/mypy src/layerwatch

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .benchmarks .layerwatch-cache
