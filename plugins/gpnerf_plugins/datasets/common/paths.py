"""A dataset root given in a config: a relative path is taken from the directory the command was started in."""

from __future__ import annotations

from pathlib import Path


def from_launch_dir(root: str) -> Path:
    """``root`` with ``~`` expanded; a relative path is joined to the launch directory.

    The launch directory is Hydra's original working directory inside a Hydra run (which may have changed into its
    output folder), else the current one.
    """
    path = Path(root).expanduser()
    if path.is_absolute():
        return path
    base = Path.cwd()
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.utils import get_original_cwd

        if HydraConfig.initialized():
            base = Path(get_original_cwd())
    except ImportError:
        pass
    return base / path
