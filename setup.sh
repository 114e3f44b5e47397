#!/usr/bin/env bash
# Creates ./.venv and installs gpnerf-core with its test tools. Safe to re-run.
# CPU machines get torch 2.13.0 (CPU build) first; torchvision is kept out (see docs/install.md).
# To use your own (e.g. CUDA) torch, install it into .venv before running this script.
set -euo pipefail
cd "$(dirname "$0")"
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  .venv/bin/pip install --quiet --disable-pip-version-check "torch==2.13.0"
fi
.venv/bin/pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test]"
.venv/bin/python -c "import torch, gpnerf_core; print(f'gpnerf-core {gpnerf_core.__version__} ready (torch {torch.__version__})')"
