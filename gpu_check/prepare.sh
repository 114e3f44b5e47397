#!/usr/bin/env bash
# Fill gpu_check/wheels and gpu_check/cache (git-ignored) for gpu_check/run.sh on a machine without network.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
mkdir -p gpu_check/wheels gpu_check/cache
# Pure-Python packages as wheels (antlr4's runtime is published as a source archive only: built here) ...
"$PYTHON" -m pip wheel --quiet --disable-pip-version-check --no-deps -w gpu_check/wheels \
  "hydra-core>=1.3,<1.4" "omegaconf>=2.3,<2.4" "antlr4-python3-runtime==4.9.3" "kornia>=0.7"
# ... and the compiled ones for the image's Python (3.12) and this one (3.11, for trying the install here).
for version in 3.11 3.12; do
  "$PYTHON" -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: \
    --python-version "$version" --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux_2_28_x86_64 -d gpu_check/wheels kornia-rs pycocotools
done
# gsplat for the rasterizer step (optional: its CUDA kernels compile on first use where the GPU image has nvcc; without
# it the step times the torch backend alone and says why)
"$PYTHON" -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: -d gpu_check/wheels \
  gsplat jaxtyping wadler-lindig || echo "gsplat: no wheel downloaded; the rasterizer step will time the torch backend alone"
"$PYTHON" - <<'PY'
"""Render the scene sets of gpu_check/checks.py's SCENE_SETS into gpu_check/cache under the cache key a machine
without pybullet computes (its version reads "unknown" there), so the checks find them instead of rendering."""
import shutil
import sys
from pathlib import Path

sys.path.insert(0, "gpu_check")
from checks import SCENE_SETS  # noqa: E402

import gpnerf_plugins.datasets.embedded.generation as generation
from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose

cache = Path("gpu_check/cache/embedded_scenes")
cache.mkdir(parents=True, exist_ok=True)
for name, overrides in SCENE_SETS.items():
    params = build_components(compose(overrides)).dataset.params
    real = generation._pybullet_version
    generation._pybullet_version = lambda: "unknown"
    try:
        target = cache / params.cache_key()
    finally:
        generation._pybullet_version = real
    if not (target / "classes.json").is_file():
        shutil.rmtree(target, ignore_errors=True)
        generation.generate(params, target)
    size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file()) / 1e6
    print(f"scene set {name}: {target} ({size:.1f} MB)")
PY
ls gpu_check/wheels
du -sh gpu_check/wheels gpu_check/cache
