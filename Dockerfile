# syntax=docker/dockerfile:1
# lowres3d detection service: runtime images for CPUs, NVIDIA GPUs and NVIDIA Jetson.
#
#   docker build -t lowres3d:cpu .                                   # x86-64 or arm64 CPU (onnxruntime)
#   docker build -t lowres3d:gpu --build-arg TARGET=gpu .            # x86-64 + NVIDIA GPU (onnxruntime-gpu, TensorRT)
#   docker build -t lowres3d:jetson --build-arg TARGET=jetson .      # Jetson Orin, JetPack 6 (build on the Jetson)
#
# The image holds only what the service needs: pipeline/ and service/ (no torch, no compilers), the
# shipped models, a non-root user. Settings are LOWRES3D_* environment variables (docs/deploy.md).

ARG TARGET=cpu
ARG CPU_BASE=python:3.11-slim-bookworm
ARG GPU_BASE=nvidia/cuda:12.6.3-cudnn-runtime-ubuntu24.04
ARG JETSON_BASE=nvcr.io/nvidia/l4t-jetpack:r36.4.0

# --------------------------------------------------------------------------- CPU (x86-64, arm64)
FROM ${CPU_BASE} AS runtime-cpu
# The versions the tests ran on (requirements/constraints.txt): an image built later ships the same ones.
COPY requirements/service-cpu.txt /tmp/requirements.txt
COPY requirements/constraints.txt /tmp/constraints.txt
RUN python -m venv /opt/venv \
    && /opt/venv/bin/pip install --no-cache-dir -r /tmp/requirements.txt -c /tmp/constraints.txt \
    && rm /tmp/requirements.txt /tmp/constraints.txt

# --------------------------------------------------------------------------- NVIDIA GPU (x86-64)
FROM ${GPU_BASE} AS runtime-gpu
# Three versions that must agree (docs/deploy.md): the base image's CUDA 12, the TensorRT the ONNX Runtime
# wheel was built with, and that wheel. Unpinned, each drifts to a CUDA 13 build: apt picks the
# "+cuda13.x" TensorRT packages of the same CUDA repository, and pip an onnxruntime-gpu >= 1.27 (CUDA 13,
# cuDNN for CUDA 13); on this CUDA 12 base both fail to load and every network silently runs on the CPU.
# onnxruntime-gpu 1.22 is built with TensorRT 10.9 for CUDA 12.0-12.8.
ARG ORT_GPU_VERSION=1.22.0
ARG TENSORRT_VERSION=10.9.0.34-1+cuda12.8
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv \
       "libnvinfer10=${TENSORRT_VERSION}" "libnvinfer-plugin10=${TENSORRT_VERSION}" \
       "libnvonnxparsers10=${TENSORRT_VERSION}" \
    && rm -rf /var/lib/apt/lists/*
COPY requirements/service-gpu.txt /tmp/requirements.txt
COPY requirements/constraints.txt /tmp/constraints.txt
RUN python3 -m venv /opt/venv \
    && /opt/venv/bin/pip install --no-cache-dir "onnxruntime-gpu==${ORT_GPU_VERSION}" -r /tmp/requirements.txt \
       -c /tmp/constraints.txt \
    && rm /tmp/requirements.txt /tmp/constraints.txt

# --------------------------------------------------------------------------- NVIDIA Jetson (JetPack 6)
FROM ${JETSON_BASE} AS runtime-jetson
# JetPack 6 ships Python 3.10 with CUDA 12.6 and TensorRT 10; its onnxruntime-gpu wheels come from the
# Jetson AI Lab index (PyPI has no CUDA builds for aarch64). requirements/constraints.txt is not used here:
# some of its versions need Python 3.11 (NumPy 2.3 and later), so this image takes the newest that run on 3.10.
ARG JETSON_INDEX=https://pypi.jetson-ai-lab.io/jp6/cu126
ARG ORT_GPU_VERSION=1.23.0
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3-venv \
    && rm -rf /var/lib/apt/lists/*
COPY requirements/service-jetson.txt /tmp/requirements.txt
RUN python3 -m venv /opt/venv \
    && /opt/venv/bin/pip install --no-cache-dir --extra-index-url "${JETSON_INDEX}" \
       "onnxruntime-gpu==${ORT_GPU_VERSION}" -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# --------------------------------------------------------------------------- the service
# hadolint ignore=DL3006
FROM runtime-${TARGET} AS service
WORKDIR /app
# Apache-2.0 asks that the licence travel with every copy of the code and weights.
COPY LICENSE /app/LICENSE
COPY pipeline/ /app/pipeline/
COPY service/ /app/service/
COPY weights/edge/ /app/weights/edge/
# INT8 (7-bit weights: the same outputs on every x86 CPU, fastest with VNNI): LOWRES3D_MODELS=/app/weights/edge-int8
# (docs/deploy.md).
COPY weights/edge-int8/ /app/weights/edge-int8/
# The video group (gid 44 in every base image, as on the host): on a Jetson the GPU device nodes belong to it,
# and a user outside it sees no CUDA device (ONNX Runtime would silently fall back to the CPU).
RUN useradd --system --uid 10001 --groups video --home-dir /app --shell /usr/sbin/nologin lowres3d \
    && mkdir -p /var/cache/lowres3d/tensorrt \
    && chown lowres3d /var/cache/lowres3d/tensorrt
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONPATH=/app \
    PYTHONUNBUFFERED=1 \
    LOWRES3D_MODELS=/app/weights/edge \
    LOWRES3D_HOST=0.0.0.0 \
    LOWRES3D_PORT=8000 \
    LOWRES3D_TRT_CACHE_DIR=/var/cache/lowres3d/tensorrt
# TensorRT builds its engines once per box and model: keep them on a volume.
VOLUME ["/var/cache/lowres3d/tensorrt"]
USER 10001
EXPOSE 8000
# No proxy: Docker passes the client's configured proxies (HTTP_PROXY, ~/.docker/config.json) into every
# container, and urllib would send the probe of the container's own loopback to that proxy (never healthy).
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; url = 'http://127.0.0.1:%s/readyz' % os.environ.get('LOWRES3D_PORT', '8000'); opener = urllib.request.build_opener(urllib.request.ProxyHandler({})); sys.exit(0 if opener.open(url, timeout=4).status == 200 else 1)"]
CMD ["python", "-m", "service"]
