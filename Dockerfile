# syntax=docker/dockerfile:1
# Rig controller image: `docker run --rm rig` runs `rig demo` (controller against the
# emulated rig in a process of its own, over a socket pair; no CAN hardware, no
# capabilities, works with --network none).
# Real rig: docs/deploy.md (--network host for SocketCAN, real-time ulimits).
# BASE: any Debian-like image with python3 (>= 3.11) and python3-venv; the test suite
# builds on a debootstrap'ed bookworm (scripts/container-image.sh) where no registry is
# reachable.

ARG BASE=python:3.11-slim

FROM ${BASE} AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md ./
# the dependencies first, in a layer of their own: a change to the code reuses it
RUN python3 -m venv /opt/rig/.venv \
    && /opt/rig/.venv/bin/pip install $(python3 -c 'import tomllib; print(" ".join( \
        tomllib.load(open("pyproject.toml", "rb"))["project"]["dependencies"]))')
COPY controller ./controller
COPY rig ./rig
COPY hil ./hil
RUN /opt/rig/.venv/bin/pip install --no-deps . \
    && /opt/rig/.venv/bin/pip check \
    && /opt/rig/.venv/bin/rig --help > /dev/null

FROM ${BASE}
# iproute2 only for deploy/setup-can.sh (creating vcan0 needs --cap-add NET_ADMIN and root)
RUN apt-get update \
    && apt-get install -y --no-install-recommends iproute2 \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/rig/.venv /opt/rig/.venv
COPY deploy/rig.example.toml /etc/rig/rig.toml
COPY deploy/setup-can.sh /opt/rig/setup-can.sh
RUN useradd --system --uid 10001 --user-group --home-dir /var/lib/rig --create-home rig
ENV PATH=/opt/rig/.venv/bin:$PATH \
    NUMBA_CACHE_DIR=/var/lib/rig/.numba-cache \
    PYTHONUNBUFFERED=1
USER rig
WORKDIR /var/lib/rig
# MCAP runs are written to ./runs (recording.directory); mount a volume to keep them
VOLUME ["/var/lib/rig/runs"]
ENTRYPOINT ["rig"]
CMD ["demo"]
