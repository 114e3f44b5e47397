"""Learning-rate groups the built-in families share (``model.lr.<group>``), each a dataclass a family's config holds as
its ``lr`` field: the groups its ``parameter_groups()`` names, with the paper's rates as defaults (``scale=cpu`` and
the experiments set the rates they train with)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SourceViewRates:
    """A generalizable family built on an extractor: the extractor, the family's own networks, the ``+head``."""

    feature_extractor: float = 5e-3
    """The extractor (``model.feature_extractor``): encoder, radiance decoder and FPN (GP-NeRF: 5e-3)."""
    transformer: float = 1e-5
    """The family's own networks: GNT's aggregators and semantic adaptor (GP-NeRF: 1e-5, fine-tuning GNT weights),
    another family's field networks."""
    head: float = 5e-5
    """The perception head (GP-NeRF: 5e-5)."""


@dataclass
class FieldRates:
    """A per-scene NeRF's own field."""

    field: float = 5e-4
    """The field's networks (a NeRF MLP, a grid's small networks; Semantic-NeRF: 5e-4)."""


@dataclass
class GridFieldRates(FieldRates):
    """A per-scene NeRF whose field may be a hash grid (``model.field=grid``)."""

    grid: float = 1e-2
    """The grid's hash tables (Instant-NGP: 1e-2)."""
