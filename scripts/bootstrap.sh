#!/usr/bin/env bash
# Set up nanostage on a fresh machine: a virtualenv in .venv with the pinned
# dependencies and the package itself. Idempotent; safe to run repeatedly.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
# compile the numba kernels once, with progress (minutes on a fresh machine, seconds when cached);
# NANOSTAGE_NO_WARMUP=1 skips it (the first run then compiles what it needs)
if [ -z "${NANOSTAGE_NO_WARMUP:-}" ]; then
  .venv/bin/python -m experiment_runner.apps.warmup
fi
