#!/usr/bin/env bash
# The prepared GPU check (gpu_check/README.md): offline install over the image's CUDA torch, then gpu_check/checks.py.
#   bash gpu_check/run.sh                       on the GPU machine (OUT=<folder>, default /tmp/gpu_check)
#   GPU_CHECK_DRY_RUN=1 PYTHON=.venv/bin/python bash gpu_check/run.sh    the same steps on this CPU, tiny
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu_check}
if [ -n "${GPU_CHECK_DRY_RUN:-}" ]; then
  PY=${PYTHON:-.venv/bin/python}
else
  [ -d gpu_check/wheels ] && [ -d gpu_check/cache ] || { echo "run gpu_check/prepare.sh first (and carry gpu_check/wheels, gpu_check/cache)" >&2; exit 2; }
  BASE=${PYTHON:-python3}
  VENV=/tmp/gpnerf-gpu-venv
  "$BASE" -m venv --system-site-packages "$VENV"   # the image's torch, numpy, scipy, ... stay visible
  PY="$VENV/bin/python"
  version=$("$PY" -c 'import sys; print(f"cp{sys.version_info.major}{sys.version_info.minor}")')
  wheels=$(ls gpu_check/wheels/*.whl | grep -E "py3-none|${version}" )
  "$PY" -m pip install --quiet --no-index --no-deps $wheels
  if ! "$PY" -m pip install --quiet --no-index --no-deps --no-build-isolation -e . ; then
    # no setuptools/wheel able to build it offline: put the source folders on the path instead
    site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    mkdir -p /tmp/gpnerf-conf-link && ln -sfn "$PWD/conf" /tmp/gpnerf-conf-link/gpnerf_conf
    printf '%s\n%s\n%s\n' "$PWD" "$PWD/plugins" /tmp/gpnerf-conf-link > "$site/gpnerf-source.pth"
    echo "gpnerf-core on the path from $PWD (editable install not possible offline)"
  fi
fi
"$PY" -c "import torch, gpnerf_core; print(f'torch {torch.__version__}, cuda {torch.cuda.is_available()}, gpnerf-core {gpnerf_core.__version__}')"
exec "$PY" gpu_check/checks.py "$OUT"
