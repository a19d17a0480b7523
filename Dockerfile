# One image for every hoi-refine role: API (`hoi-refine serve`), Ray head (`hoi-refine ray-head`) and
# workers (`hoi-refine worker --ray-address ... --ray-node`). docker-compose.yml picks the role per service.
#
# The base only needs Python 3.11 with `python` and `pip` on PATH. Without Docker Hub, build a local one from
# Debian's packages and use it:
#   docker/build_base_image.sh    # -> hoi-refine-base:bookworm (debootstrap, this machine's CA bundle)
#   docker build --network host --build-arg BASE_IMAGE=hoi-refine-base:bookworm -t hoi-refine:latest .
# (`make image` does both; `make verify-image RESULTS=DIR` runs `hoi-refine verify` in the image: README, Containers.)
# The image is lean on purpose: no torch (the `mano` extra is optional and not installed here).
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    # Headless offscreen rendering for the workers' preview videos (worker/visual): Mesa's EGL, no GPU needed.
    MUJOCO_GL=egl \
    HOI_REFINE_VAR_DIR=/var/lib/hoi-refine

# Mesa's EGL and software OpenGL driver: the workers render each finished job's preview video with them.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libgl1 libgl1-mesa-dri \
    && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 hoi \
    && mkdir -p /var/lib/hoi-refine \
    && chown hoi /var/lib/hoi-refine

WORKDIR /app
# Dependencies first (cached layer): only pyproject.toml changes invalidate it. The stub package gets an empty
# README.md (pyproject's `readme`), so editing the real one does not reinstall every dependency.
COPY pyproject.toml ./
RUN mkdir -p common worker service migrations \
    && touch README.md common/__init__.py worker/__init__.py service/__init__.py migrations/__init__.py \
    && pip install . \
    && pip uninstall -y hoi-refine \
    && rm -rf build
COPY README.md ./
COPY common ./common
COPY worker ./worker
COPY service ./service
COPY migrations ./migrations
COPY alembic.ini ./
# No build/ is left from the stub (removed above): setuptools would keep its empty __init__.py files over the real
# ones, whose copies are older.
RUN pip install --no-deps . && rm -rf build && hoi-refine --help >/dev/null

USER hoi
EXPOSE 8000
# The API by default; compose overrides the command for the Ray head and the workers.
CMD ["hoi-refine", "serve", "--host", "0.0.0.0", "--port", "8000"]
