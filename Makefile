# Two commands for a newcomer: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast lint typecheck bench-replay compose-test image verify-image pose-basis clean

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

# The project's container image (needs a running dockerd; the base's first build needs root and debootstrap).
# Minutes, so not part of `make test`. The base (docker/build_base_image.sh) is built only when absent. BUILD is the
# build context, e.g. `make image BUILD=/work/wt/x IMAGE=hoi-refine:x` builds another checkout with this base.
IMAGE ?= hoi-refine:latest
BASE_IMAGE ?= hoi-refine-base:bookworm
BUILD ?= .

image:
	docker/build_base_image.sh $(BASE_IMAGE)
	docker build --network host --build-arg BASE_IMAGE=$(BASE_IMAGE) -t $(IMAGE) $(BUILD)

# `hoi-refine verify` inside the image: RESULTS is a result file or a folder of them (mounted read-only at /data,
# so files must be readable by the image's user, uid 10001); VERIFY_ARGS go to verify (e.g. --jobs 2), DOCKER_ARGS to
# docker run (e.g. -e OPENBLAS_CORETYPE=Haswell to force other kernels inside).
verify-image:
	@test -n "$(RESULTS)" || { echo "usage: make verify-image RESULTS=FILE_OR_DIR [IMAGE=...] [VERIFY_ARGS=...]" >&2; exit 2; }
	@R="$$(realpath "$(RESULTS)")" && if [ -d "$$R" ]; then D="$$R" T=/data; else D="$$(dirname "$$R")" T="/data/$$(basename "$$R")"; fi \
	  && set -x && docker run --rm --network host -v "$$D:/data:ro" $(DOCKER_ARGS) $(IMAGE) hoi-refine verify "$$T" $(VERIFY_ARGS)

pose-basis: $(STAMP)
	$(BIN)/python -m worker.hand.pose_basis_build

clean:
	rm -rf $(VENV) var .pytest_cache .mypy_cache .ruff_cache
