# crowdrl — every target creates/reuses the virtualenv in .venv first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
export PYTHONHASHSEED ?= 0

.PHONY: install lint test test-slow demo bench api-docs clean

install: $(STAMP)

# torch is installed first and pinned to the CPU wheel that pip finds locally; the
# project's range (>=2.11,<2.15) then accepts it instead of pulling a CUDA build.
# pyrvo (RVO2 2.0.3) is the reference ORCA for tests and benchmarks; it declares a heavy
# dependency it does not use, hence --no-deps.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[dev]"
	$(PY) -m pip install --quiet --no-deps "pyrvo==0.4.3"
	touch $(STAMP)

# test files run in parallel, one per worker (a file's tests stay together, in order, sharing
# its module fixtures); TEST_WORKERS=1 runs them one after another. The 15 slowest tests are
# listed at the end, to keep the suite's 10-minute budget in sight.
TEST_WORKERS ?= 2
# the linter (ruff, configured in pyproject.toml) runs first: a lint error fails `make test`
lint: $(STAMP)
	$(PY) -m ruff check .

test: lint
	$(PY) -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile --durations=15

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

demo: $(STAMP)
	$(PY) experiments/demo.py

bench: $(STAMP)
	$(PY) experiments/bench_env.py
	$(PY) experiments/bench_train.py

# the API reference with signatures, generated from the docstrings (open build/api/index.html)
api-docs: $(STAMP)
	$(PY) experiments/api_docs.py --out build/api

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis build src/*.egg-info
