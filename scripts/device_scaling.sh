#!/usr/bin/env bash
# Scaling experiments of issue 27 on a many-core machine without internet (the `device` tool's
# 16-core machines): warms the numba cache, then runs scripts/device_scaling.py (campaign
# trials/s on 1..N workers and Dask, in-process thread scaling now and with the chunks of
# before, the thread-scaling hypotheses). Results: $OUT/scaling.json, $OUT/scaling.md, $OUT/log.txt.
#
#   scripts/device_wheels.sh                      # here, once: .device-wheels/ (~6 MB)
#   OUT=/tmp/x scripts/device_scaling.sh --tiny   # a check on a small machine (about 2 minutes)
#   device run, carry [".device-wheels"], timeout_s 600:
#       bash scripts/device_scaling.sh            # about 5-7 minutes on 16 cores
#
# Python: .venv/bin/python where it works, else the machine's python3 (it needs numpy, numba,
# scipy, PyYAML) with the wheels of .device-wheels/ installed into /tmp/nanostage-site.
# WARM_LIMIT (default 200 s) bounds the compile; BUDGET (default 300 s) the measurements.
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
OUT=${OUT:-$ROOT/out/device_scaling}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 OUT
exec > >(tee "$OUT/log.txt") 2>&1

PY=""
if [ -x .venv/bin/python ] && .venv/bin/python -c "import numba, pydantic, distributed" 2>/dev/null; then
  PY=$ROOT/.venv/bin/python
else
  PY=$(command -v python3)
  if [ -d .device-wheels ]; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/nanostage-site .device-wheels/*.whl || { echo "device_scaling: wheel install failed"; exit 1; }
    export PYTHONPATH=/tmp/nanostage-site
  fi
fi
export PYTHONPATH=$ROOT${PYTHONPATH:+:$PYTHONPATH}
"$PY" -c "import numba, numpy, scipy, yaml, pydantic; print('python', __import__('sys').version.split()[0], \
'numba', numba.__version__, 'numpy', numpy.__version__)" || {
  echo "device_scaling: $PY lacks a package the campaign path needs (run scripts/device_wheels.sh here and carry .device-wheels)"
  exit 1
}
nproc; (lscpu 2>/dev/null | grep -E "^(Model name|Thread|Core|Socket|CPU\(s\)|NUMA node\(s\))") || true
uptime

echo "== warm-up: compiling the batch engine (limit ${WARM_LIMIT:-200} s)"
t0=$(date +%s)
timeout "${WARM_LIMIT:-200}" "$PY" -m experiment_runner.apps.warmup batch
rc=$?
warm=$(( $(date +%s) - t0 ))
[ $rc -eq 0 ] || echo "device_scaling: warm-up exit $rc after ${warm} s (124: its time limit); measuring anyway"

echo "== measurements (budget ${BUDGET:-300} s)"
timeout $(( ${BUDGET:-300} + 60 )) "$PY" scripts/device_scaling.py --warmup-s "$warm" --budget "${BUDGET:-300}" "$@"
echo "device_scaling: exit $? after $(( $(date +%s) - t0 )) s; results in $OUT"
