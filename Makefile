# Two commands for a newcomer: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast lint typecheck bench-replay compose-test pose-basis clean

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,mano]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hoi-refine demo

# The suite's PostgreSQL half runs against HOI_REFINE_TEST_POSTGRES_URL when set, else against a local server that
# answers on 127.0.0.1:5432 (.ci/local-postgres-url, as CI does); pytest's header and summary say which databases ran.
POSTGRES_URL = $${HOI_REFINE_TEST_POSTGRES_URL:-$$(sh .ci/local-postgres-url)}

test: $(STAMP)
	$(BIN)/ruff check common worker service migrations tests bench
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache
	HOI_REFINE_TEST_POSTGRES_URL="$(POSTGRES_URL)" $(BIN)/python -m pytest

test-fast: $(STAMP)
	HOI_REFINE_TEST_POSTGRES_URL="$(POSTGRES_URL)" $(BIN)/python -m pytest -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check common worker service migrations tests bench
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache

bench-replay: $(STAMP)
	$(BIN)/python bench/replay.py

# The container stack on this machine (needs dockerd, docker-compose, debootstrap, root, the host's PostgreSQL):
# build the images, start API + Ray head + 2 worker containers, kill one mid-job, check every job ends once.
# Minutes, so not part of `make test`. Writes bench/results/compose.md.
compose-test: $(STAMP)
	$(BIN)/python bench/compose_test.py --out bench/results/compose.md

pose-basis: $(STAMP)
	$(BIN)/python -m worker.hand.pose_basis_build

clean:
	rm -rf $(VENV) var .pytest_cache .mypy_cache .ruff_cache
