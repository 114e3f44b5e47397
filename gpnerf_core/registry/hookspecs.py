"""pluggy hook specifications of gpnerf-core.

Every hook is named ``gpnerf_register_<kind>s`` and returns a list of ``ComponentSpec``. The host calls each
hook once when it builds the registry, walks the implementations one by one so it knows which plugin
provided each spec, and refuses duplicates. Hooks take no arguments so implementations stay pure data;
a plugin that needs to compute its specs does it inside the hook.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    from gpnerf_core.interfaces import StressCase
    from gpnerf_core.registry.specs import ComponentSpec, DataTool

PROJECT_NAME = "gpnerf"
hookspec = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


@hookspec
def gpnerf_register_models() -> list[ComponentSpec]:
    """Model families, implementing ``gpnerf_core.interfaces.model.ModelFamily``: what renders a target view's rays
    (GNT with GP-NeRF's semantic field is ``gnt``).

    Each spec's config subclasses ``gpnerf_core.ModelConfig`` (the fields every family has: samples per ray, source
    views, ``init``). The factory is called with the config's own fields (not ``num_source_views``, ``init`` and
    ``init_strict``, which the core reads) and ``parts`` (``ModelParts``), through which it builds the extractor,
    aggregators or head it is made of from their own config groups.

    Returns:
        Specs whose names become options of the Hydra group ``model`` (``model=<name>``).
    """


@hookspec
def gpnerf_register_feature_extractors() -> list[ComponentSpec]:
    """Image encoders, implementing ``gpnerf_core.interfaces.FeatureExtractor``.

    Called once per registry build. Each spec's factory is called with the config fields (minus ``name``)
    as keyword arguments.

    Returns:
        Specs whose names become options of the Hydra group ``model/feature_extractor`` (a part a model family
        builds, mounted under the model: ``model.feature_extractor.<option>``).
    """


@hookspec
def gpnerf_register_field_aggregators() -> list[ComponentSpec]:
    """Per-sample aggregators over views, implementing ``FieldAggregator``.

    The factory also receives ``in_dim`` (3 + the extractor's radiance width) from the pipeline.

    Returns:
        Specs for the Hydra group ``model/field_aggregator`` (a part, under the model).
    """


@hookspec
def gpnerf_register_ray_aggregators() -> list[ComponentSpec]:
    """Along-ray aggregators, implementing ``RayAggregator``.

    The factory also receives ``in_dim`` (the field aggregator's token width).

    Returns:
        Specs for the Hydra group ``model/ray_aggregator`` (a part, under the model).
    """


@hookspec
def gpnerf_register_heads() -> list[ComponentSpec]:
    """Perception heads, implementing ``PerceptionHead``.

    The factory also receives ``in_dim`` and ``in_levels`` (the semantic map's width and number of
    levels) and ``num_outputs``: the dataset's class count, or ``slots + 1`` for a head whose class sets
    ``predicts = Predicts.INSTANCES`` (its config must then have a ``slots`` field).

    Returns:
        Specs for the Hydra group ``head`` (an add-on group: select with ``+head=<name>``).
    """


@hookspec
def gpnerf_register_losses() -> list[ComponentSpec]:
    """Loss sets (named, weighted groups of terms), implementing ``LossSet``.

    Returns:
        Specs for the Hydra group ``loss`` (an add-on group: select with ``+loss=<name>``).
    """


@hookspec
def gpnerf_register_datasets() -> list[ComponentSpec]:
    """Scene datasets, implementing ``SceneDataset``.

    The factory receives its config fields; relative paths are resolved by the dataset against the
    directory the command was started in.

    Returns:
        Specs for the Hydra group ``dataset``.
    """


@hookspec
def gpnerf_register_view_selectors() -> list[ComponentSpec]:
    """Source-view selectors, implementing ``ViewSelector``.

    Returns:
        Specs for the Hydra group ``view_selector``.
    """


@hookspec
def gpnerf_register_depth_sources() -> list[ComponentSpec]:
    """Depth sources for ``model.sampler=depth``, implementing ``DepthSource``: a cheap depth per ray from the source
    views before any rendering pass.

    Returns:
        Specs for the Hydra group ``depth_source`` (an add-on group: select with ``+depth_source=<name>``).
    """


@hookspec
def gpnerf_register_feature_providers() -> list[ComponentSpec]:
    """Feature providers, implementing ``gpnerf_core.FeatureProvider``: frozen 2D models giving each frame a dense
    feature map ``[C, h, w]`` (XFeat's descriptors, a user's CLIP or LSeg maps read from files, a trained checkpoint's
    extractor), which a feature field distils and queries compare against.

    Called once per registry build. Each spec's factory is called with the config fields (minus ``name``) as keyword
    arguments and nothing else; a provider whose package or weights file is missing refuses in its constructor with a
    ``ConfigError`` naming the path and the extra to install. The core reads its features through the on-disk cache
    (``gpnerf_core.frame_features``), keyed by ``FeatureProvider.fingerprint()``: ``compute`` runs once per frame and
    config, from ``python -m gpnerf_core data features`` or at first use.

    Returns:
        Specs for the Hydra group ``feature_provider`` (an add-on group: select with ``+feature_provider=<name>``,
        options ``feature_provider.<field>``).
    """


@hookspec
def gpnerf_register_data_tools() -> list[DataTool]:
    """Subcommands of ``python -m gpnerf_core data`` (checkers, converters, generators).

    Each tool parses its own arguments and returns an exit code; user errors are raised as
    ``gpnerf_core.errors.GpnerfError`` and printed on one line by the CLI.

    Returns:
        ``DataTool`` records; a name registered twice is an error naming both providers.
    """


@hookspec
def gpnerf_register_stress_cases() -> list[StressCase]:
    """Conditions ``python -m gpnerf_core stress`` evaluates trained models under (source views, pose noise, ...).

    Returns:
        ``StressCase`` instances (``gpnerf_core.interfaces.StressCase``); a name registered twice is an error
        naming both providers.
    """


@hookspec
def gpnerf_config_searchpaths() -> list[str]:
    """Folders of Hydra configs the plugin ships beside its components: presets, found as if they were in gpnerf-core's
    own ``conf/``.

    Called once per registry build; gpnerf-core's one Hydra ``SearchPathPlugin`` (``hydra_plugins/
    gpnerf_core_searchpath``) appends each folder to the config search path after ``conf/``, for every command that
    composes a config. What a folder holds is used by path:

    - ``experiment/<name>.yaml``: ``+experiment=<name>`` (``# @package _global_``, as the built-in experiments);
    - ``scale/<scale>/<model>.yaml``: the plugin's family's sizes at that scale (``scale=cpu`` picks it for
      ``model=<model>``); ``scale/<scale>/<kind>/<name>.yaml``: a part's (``model.<kind>``).

    A file whose path is also a built-in config's, or another plugin's, is refused naming both (presets add to the
    built-in ones, never replace them): every command that composes a config then stops with one line, and
    ``python -m gpnerf_core plugins`` lists it as a problem.

    Returns:
        Hydra search paths: ``pkg://<package>.<folder>`` (a package folder with an ``__init__.py``, installed with the
        plugin: ``pkg://gpnerf_fancy.conf``) or ``file://<absolute folder>``.
    """
