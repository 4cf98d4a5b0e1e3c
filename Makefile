# Two commands a fresh machine needs: `make demo` and `make test` (`make wheel-check`: the built wheel, offline).
# Without ../shared (or with PIXIE_SHARED=/nonexistent) the demo uses a generated part and LM-O tests skip.
# Both install exactly the versions locked in constraints.txt (refresh it with `make lock`).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PIP_VERSION := 26.3
EXTRAS := test,synth,ray

.PHONY: demo test test-fast lint setup clean bench lock wheel-check

$(STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q "pip==$(PIP_VERSION)"
	$(BIN)/pip install -q -c constraints.txt -e ".[$(EXTRAS)]"
	$(BIN)/pip check
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m pixie demo

# One pytest process per core (TEST_WORKERS, 2 here), one thread each; every test file runs whole in one worker
# (--dist loadfile), so its fixtures are built once; the longest files start first (tests/conftest.py).
# TEST_WORKERS=0 runs everything in this process.
TEST_WORKERS ?= 2

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The inner loop: everything but the tests marked slow (the full end-to-end runs).
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check src tests bench

# The installed wheel, outside the repo, offline, with no shared data: `pixie demo` and `pixie estimate` must run.
wheel-check:
	PY=$(PY) PIP_VERSION=$(PIP_VERSION) bash tools/wheel_check.sh

# Re-resolve every dependency from pyproject.toml (only torch pinned) in a throw-away venv and write
# the full lock to constraints.txt. Review the diff, run `make clean test`, and commit it.
lock:
	rm -rf .lockenv
	$(PY) -m venv .lockenv
	.lockenv/bin/pip install -q "pip==$(PIP_VERSION)"
	.lockenv/bin/pip install -q "torch==2.13.0" -e ".[$(EXTRAS)]"
	{ echo "# Full lock of every dependency pixie installs (make lock; $$(date -u +%F), Python $$($(PY) -c 'import platform; print(platform.python_version())'))."; \
	  echo "# torch stays 2.13.0: on the project machines that is the local CPU wheel; any other spec pulls CUDA builds."; \
	  .lockenv/bin/pip freeze --exclude-editable | grep -v '^#' | sed 's/^torch==2.13.0+.*/torch==2.13.0/'; } > constraints.txt.tmp
	mv constraints.txt.tmp constraints.txt
	rm -rf .lockenv

clean:
	rm -rf $(VENV) out
