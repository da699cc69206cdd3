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
COPY training ./training
COPY controller ./controller
COPY firmware_bridge ./firmware_bridge

FROM base AS runtime
RUN pip install --no-cache-dir . \
    && useradd --uid 10001 --no-create-home --shell /usr/sbin/nologin qnav
USER 10001
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s --retries=3 \
    CMD ["qnav", "--version"]
ENTRYPOINT ["qnav"]
CMD ["--help"]

FROM base AS train
# torch's CPU wheels: the default index would pull gigabytes of CUDA libraries.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN pip install --no-cache-dir --extra-index-url "${TORCH_INDEX}" "/opt/qnav[train]" \
    && useradd --uid 10001 --create-home --shell /usr/sbin/nologin qnav
USER 10001
WORKDIR /home/qnav
HEALTHCHECK --interval=60s --timeout=5s --start-period=10s --retries=3 \
    CMD ["qnav", "--version"]
ENTRYPOINT ["qnav"]
CMD ["--help"]
