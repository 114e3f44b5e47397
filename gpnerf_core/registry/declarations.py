"""What a component's config dataclass declares about itself for the core and its tools to read: the parts a model
family builds (``part``), which the core mounts under ``model`` as config groups of their own.

A declaration is dataclass field metadata, so it sits on the field it is about and costs the component nothing at run
time: the config stays a plain dataclass (Hydra's schema), its factory never sees the metadata.
"""

from __future__ import annotations

import dataclasses
from typing import Any

PART = "gpnerf_part"
"""Field metadata key: the field holds one of the parts a model family builds; its value is the default option."""


def part(default: str | None) -> Any:
    """A model family config's field that holds one of the parts the family builds: the field's name is the part's
    kind (``feature_extractor``, ``field_aggregator``, ``ray_aggregator``), typed ``Any``, and the core mounts the kind's
    Hydra group under ``model`` (``model/feature_extractor=mvsnet``, keys ``model.feature_extractor.<option>``).

        feature_extractor: Any = part("resunet_fpn")

    Args:
        default: the option chosen unless a config or the command line chooses another (None: none by default).
    """
    return dataclasses.field(default=None, metadata={PART: default})


def declared_parts(config: type) -> dict[str, str | None]:
    """``kind -> default option`` of the parts a model family config declares (``part``), in field order."""
    if not dataclasses.is_dataclass(config):
        return {}
    return {f.name: f.metadata[PART] for f in dataclasses.fields(config) if PART in f.metadata}
