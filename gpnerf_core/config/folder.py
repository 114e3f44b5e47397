"""Where gpnerf-core's own Hydra configs are: the ``conf/`` folder, installed as the package ``gpnerf_conf``."""

from __future__ import annotations

from pathlib import Path


def config_dir() -> str:
    """The folder of the primary config (``conf/``, installed as the package ``gpnerf_conf``)."""
    import gpnerf_conf

    return str(Path(gpnerf_conf.__file__).resolve().parent)
