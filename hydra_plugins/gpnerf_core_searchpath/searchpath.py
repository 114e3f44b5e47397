"""gpnerf-core's one Hydra ``SearchPathPlugin``: appends the config folders gpnerf plugins ship
(``gpnerf_config_searchpaths``; ``gpnerf_core.config.presets``) after gpnerf-core's own ``conf/``, so a plugin's
``experiment/<name>.yaml`` is ``+experiment=<name>`` and its ``scale/<scale>/<model>.yaml`` sizes its family.

Hydra imports every module of the ``hydra_plugins`` namespace package (which has no ``__init__.py``) and calls the
plugin for every app it composes; this one acts only where the search path holds gpnerf-core's config folder, and
imports gpnerf-core only then.
"""

from __future__ import annotations

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class GpnerfSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        if not any(_is_gpnerf_conf(element.path) for element in search_path.get_path()):
            return
        from gpnerf_core.config.presets import plugin_search_paths

        for provider, path in plugin_search_paths():
            search_path.append(provider=provider, path=path)


def _is_gpnerf_conf(path: str | None) -> bool:
    """``path`` is gpnerf-core's config folder (as a file path, or the ``gpnerf_conf`` package)."""
    if not path:
        return False
    if path.startswith("pkg://"):
        return path[len("pkg://"):].strip("/").replace("/", ".") == "gpnerf_conf"
    from pathlib import Path

    from gpnerf_core.config.folder import config_dir

    return Path(path.removeprefix("file://")).resolve() == Path(config_dir()).resolve()
