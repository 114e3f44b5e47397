"""The version of gpnerf-core and the software versions a checkpoint records."""

from __future__ import annotations

import platform

import torch

__version__ = "0.1.0"
"""gpnerf-core's version (``pyproject.toml`` holds the same)."""


def software_versions() -> dict[str, str]:
    """``{"gpnerf_core", "torch", "python"}`` versions of this process."""
    return {"gpnerf_core": __version__, "torch": str(torch.__version__), "python": platform.python_version()}
