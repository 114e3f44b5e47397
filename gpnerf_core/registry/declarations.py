"""What a component's config dataclass declares about itself for the core and its tools to read: the parts a model
family builds (``part``), which the core mounts under ``model`` as config groups of their own, and the fields ``size``
may turn down (``size_knob``), with how.

A declaration is dataclass field metadata, so it sits on the field it is about and costs the component nothing at run
time: the config stays a plain dataclass (Hydra's schema), its factory never sees the metadata.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

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


KNOB = "gpnerf_size_knob"
"""Field metadata key: the field is a size knob (``SizeKnob``) that ``size`` turns down."""


@dataclass(frozen=True)
class SizeKnob:
    """How ``size`` shrinks a config field that costs time and memory.

    Attributes:
        label: a short name for tables and ``size.knobs`` (``transformer width``).
        levels: ``reference value -> smaller values to try``, largest first (``fractions``, ``fewer``, ... or any
            function of an int): values the component accepts.
        needs: an add-on kind the field only matters with (``head``: a semantic branch that only a head decodes);
            without one configured the knob is not sized.
    """

    label: str
    levels: Callable[[int], list[int]]
    needs: str | None = None


def size_knob(default: int, label: str, levels: Callable[[int], list[int]], *, needs: str | None = None) -> Any:
    """A config field that ``size`` may turn down, declared where it is defined:

        width: int = size_knob(64, "transformer width", fractions(8, 8, 0.75, 0.5))

    A subclass that only changes the default (``coarse_samples: int = 32``) keeps the declaration of the field it
    redefines (``declared_knobs``)."""
    return dataclasses.field(default=default, metadata={KNOB: SizeKnob(label, levels, needs)})


def declared_knobs(config: type) -> dict[str, SizeKnob]:
    """``field name -> SizeKnob`` of a config dataclass, in field order: each field's own declaration, else that of
    the nearest base class declaring the same field."""
    if not dataclasses.is_dataclass(config):
        return {}
    knobs = {}
    for f in dataclasses.fields(config):
        for cls in config.__mro__:
            declared = getattr(cls, "__dataclass_fields__", {}).get(f.name)
            if declared is not None and KNOB in declared.metadata:
                knobs[f.name] = declared.metadata[KNOB]
                break
    return knobs


def fractions(multiple: int, minimum: int, *fractions: float) -> Callable[[int], list[int]]:
    """Levels: these fractions of the reference, rounded to a multiple of ``multiple`` and at least ``minimum``."""
    def levels(reference: int) -> list[int]:
        values = [max(minimum, int(round(reference * f / multiple)) * multiple) for f in fractions]
        return sorted({v for v in values if v < reference}, reverse=True)

    return levels


def fewer(*steps: int, minimum: int = 1) -> Callable[[int], list[int]]:
    """Levels: the reference minus each of ``steps``, at least ``minimum``."""
    def levels(reference: int) -> list[int]:
        return sorted({reference - s for s in steps if reference - s >= minimum}, reverse=True)

    return levels


def halved_or_none(reference: int) -> list[int]:
    """Levels: half the reference, then 0 (a count that may be left out: a fine pass)."""
    return sorted({v for v in (reference // 2, 0) if v < reference}, reverse=True)


def one_fewer_or_halved(reference: int) -> list[int]:
    """Levels: one fewer, then half (a count of at least 1: blocks)."""
    return sorted({v for v in (reference - 1, reference // 2) if 1 <= v < reference}, reverse=True)
