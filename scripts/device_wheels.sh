#!/usr/bin/env bash
# Fetch, here (where the package registry is reachable), the wheels that scripts/device_scaling.sh
# installs on a machine without internet whose Python (3.12, x86-64) has numpy, numba, scipy and
# PyYAML but not the rest of what the campaign path and Dask import. Into .device-wheels/ (ignored).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
PYVER=${DEVICE_PYTHON_VERSION:-3.12}
mkdir -p .device-wheels
"$PY" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version "$PYVER" \
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .device-wheels \
  pydantic==2.14.3 pydantic_core==2.50.4 annotated-types typing-inspection typing-extensions \
  dask==2026.8.0 distributed==2026.8.0 tornado==6.6.1 zict==3.0.0 tblib==3.2.2 partd==1.4.2 locket==1.0.0 \
  toolz==1.2.0 cloudpickle==3.1.3
du -sh .device-wheels
