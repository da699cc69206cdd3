# syntax=docker/dockerfile:1
# Two targets: `runtime` has the onboard daemons only (no torch), `train` adds the learner.
#   docker buildx build --platform linux/amd64,linux/arm64 --target runtime -t qnav:runtime .
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /opt/qnav
COPY pyproject.toml README.md ./
COPY qnav ./qnav
COPY contracts ./contracts
COPY sim ./sim
COPY simcar ./simcar
COPY training ./training
COPY controller ./controller
COPY firmware_bridge ./firmware_bridge
COPY lab ./lab

FROM base AS runtime
RUN pip install --no-cache-dir . \
    && useradd --uid 10001 --no-create-home --shell /usr/sbin/nologin qnav
USER 10001
# The controller, the bridge and the recorder rewrite this file from their working loops once a
# second (contracts/health.py); `qnav health` fails when the newest beat is over 5 s old.
ENV QNAV_HEALTH_FILE=/tmp/qnav-health.json
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
    CMD ["qnav", "health"]
ENTRYPOINT ["qnav"]
CMD ["--help"]

FROM base AS train
# torch's CPU wheels: the default index would pull gigabytes of CUDA libraries.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN pip install --no-cache-dir --extra-index-url "${TORCH_INDEX}" "/opt/qnav[train]" \
    && useradd --uid 10001 --create-home --shell /usr/sbin/nologin qnav
USER 10001
WORKDIR /home/qnav
# Training is a batch job, not a daemon: it has no loop to watch (its progress.csv shows life).
HEALTHCHECK NONE
ENTRYPOINT ["qnav"]
CMD ["--help"]
