"""The primary config composed without running it, and what Hydra needs to compose it (the config folder, the schema,
the run-folder resolver)."""

from __future__ import annotations

from typing import Any

from gpnerf_core.config.folder import config_dir
from gpnerf_core.config.schema import RootConfig

__all__ = ["compose", "config_dir", "register_schema", "run_dir_resolver"]


def run_dir_resolver(out_dir: str, default: str) -> str:
    """``hydra.run.dir``: ``out_dir`` when set, else Hydra's dated default, so nothing lands under ``outputs/``."""
    return out_dir or default


def register_schema() -> None:
    """Store the schema in Hydra's ConfigStore, register the resolvers ``conf/config.yaml`` uses, and register
    gpnerf-core's search-path plugin (plugins' presets) with Hydra itself: Hydra finds plugins by listing the
    ``hydra_plugins`` namespace, which misses a module an editable install serves through its import hook."""
    from hydra.core.config_store import ConfigStore
    from hydra.core.plugins import Plugins
    from omegaconf import OmegaConf

    from hydra_plugins.gpnerf_core_searchpath.searchpath import GpnerfSearchPathPlugin

    ConfigStore.instance().store(name="gpnerf_schema", node=RootConfig)
    OmegaConf.register_new_resolver("gpnerf_run_dir", run_dir_resolver, replace=True)
    Plugins.instance().register(GpnerfSearchPathPlugin)


def compose(overrides: list[str] | tuple[str, ...] = ()) -> Any:
    """The config ``python -m gpnerf_core run <overrides>`` would run, composed without running it.

    For notebooks, tests and scripts: ``compose(["+head=unet", "+loss=dgs", "train.steps=10"])``.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from gpnerf_core.config.presets import check_presets
    from gpnerf_core.registry.components import get_registry

    check_presets(get_registry())  # a plugin's preset that shadows another is refused, never composed
    register_schema()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return hydra_compose(config_name="config", overrides=list(overrides))
