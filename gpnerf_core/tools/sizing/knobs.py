"""The knobs ``size`` turns down: each a config key and the smaller values it tries, derived from the reference.

A knob whose key the composed config lacks (a third-party component without that option) is skipped with a note.
Values stay valid for the built-in components: token widths stay multiples of 8 (the ray aggregator's heads and the
attention MLP's ``width // 8``), FPN widths multiples of 4.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from omegaconf import OmegaConf


def _round_to(value: float, multiple: int, minimum: int) -> int:
    return max(minimum, int(round(value / multiple)) * multiple)


def _fractions(multiple: int, minimum: int, *fractions: float) -> Callable[[int], list[int]]:
    def levels(reference: int) -> list[int]:
        values = [_round_to(reference * f, multiple, minimum) for f in fractions]
        return sorted({v for v in values if v < reference}, reverse=True)

    return levels


def _fewer(*steps: int, minimum: int = 1) -> Callable[[int], list[int]]:
    def levels(reference: int) -> list[int]:
        return sorted({reference - s for s in steps if reference - s >= minimum}, reverse=True)

    return levels


@dataclass(frozen=True)
class Knob:
    """A config key that costs time and memory, and how to shrink it.

    Attributes:
        key: dotted config key (``model.coarse_samples``).
        label: short name for tables.
        levels: ``reference value -> smaller values to try``, largest first.
    """

    key: str
    label: str
    levels: Callable[[int], list[int]]


KNOBS: tuple[Knob, ...] = (
    Knob("model.coarse_samples", "coarse samples", _fractions(2, 4, 0.75, 0.5)),
    Knob("model.fine_samples", "fine samples", lambda r: sorted({v for v in (r // 2, 0) if v < r}, reverse=True)),
    Knob("model.num_source_views", "source views", _fewer(1, 2)),
    Knob("model.field_aggregator.width", "transformer width", _fractions(8, 8, 0.75, 0.5)),
    Knob("model.field_aggregator.num_blocks", "transformer blocks", lambda r: sorted({v for v in (r - 1, r // 2) if 1 <= v < r}, reverse=True)),
    Knob("model.feature_extractor.fpn_channels", "semantic width", _fractions(4, 4, 0.75, 0.5)),
    Knob("model.depth_candidates", "depth candidates", _fractions(2, 4, 0.75, 0.5)),
    Knob("model.feature_dim", "matching width", _fractions(2, 4, 0.75, 0.5)),
)


def knob_levels(cfg: Any, min_source_views: int, model_sections: tuple[str, ...] | None = None
                ) -> tuple[dict[str, tuple[int, list[int]]], list[str]]:
    """Each applicable knob's reference value and smaller levels, and notes on the knobs left out.

    Args:
        cfg: the reference config.
        min_source_views: no fewer source views are tried (the scene's coverage floor).
        model_sections: the config sections that define the model (``Components.model_sections``): a knob of a
            component kind the family never built is left out (changing it would train the same model). None: every
            section counts.
    """
    from gpnerf_core.registry.kinds import KINDS

    levels: dict[str, tuple[int, list[int]]] = {}
    notes = []
    for knob in KNOBS:
        section = knob.key.split(".")[0]
        if model_sections is not None and section in KINDS and section not in model_sections:
            notes.append(f"{knob.key}: model {cfg.model.name!r} builds no {section}; not sized")
            continue
        value = OmegaConf.select(cfg, knob.key, default=None)
        if value is None:
            notes.append(f"{knob.key}: not an option of the configured component; not sized")
            continue
        if knob.key == "model.feature_extractor.fpn_channels" and cfg.get("head") is None:
            notes.append(f"{knob.key}: no head, so no semantic branch to size")
            continue
        smaller = knob.levels(int(value))
        if knob.key == "model.num_source_views":
            smaller = [v for v in smaller if v >= min_source_views]
            if not smaller:
                notes.append(f"{knob.key}: the scene needs all {value} (coverage floor {min_source_views})")
                continue
        if smaller:
            levels[knob.key] = (int(value), smaller)
    return levels, notes


def label_of(key: str) -> str:
    return next((k.label for k in KNOBS if k.key == key), key)
