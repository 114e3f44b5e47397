"""Options of the ``semantic_nerf`` family (``+experiment=baselines/semantic_nerf``): Semantic-NeRF's, with the widths,
depths and sample counts this machine can train (each official value in the field's docstring)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from gpnerf_core import RayMarchingConfig
from gpnerf_plugins.families.rates import GridFieldRates


@dataclass
class SemanticNeRFConfig(RayMarchingConfig):
    """One scene's radiance and semantic field: a positional-encoding MLP with a view-independent semantic branch,
    coarse and fine networks, class scores volume-rendered (docs/families/semantic_nerf.md)."""

    name: str = "semantic_nerf"
    """Registry name of this model family."""
    coarse_samples: int = 32
    """Stratified samples per ray of the coarse network, uniform in depth (Semantic-NeRF: 64)."""
    fine_samples: int = 32
    """Importance samples added for the fine network, which renders coarse + fine samples (Semantic-NeRF: 128; 0 = the
    coarse network alone)."""
    num_source_views: int = 0
    """None: a per-scene model renders from its own parameters."""
    width: int = 128
    """Width of the trunk (Semantic-NeRF: 256)."""
    depth: int = 6
    """Layers of the trunk (Semantic-NeRF: 8)."""
    skip: int = 4
    """The encoded position is concatenated to the trunk after layer ``skip`` (0-based; NeRF's and Semantic-NeRF's 4:
    after the fifth layer)."""
    position_scale: float = 0.1
    """Positions are multiplied by this before the encoding (Semantic-NeRF divides by 10: its rooms span metres)."""
    position_frequencies: int = 10
    """Octaves of the position encoding (10: 63 channels)."""
    direction_frequencies: int = 4
    """Octaves of the view-direction encoding (4: 27 channels)."""
    density_noise: float = 1.0
    """Standard deviation of the noise added to the raw density in training (Semantic-NeRF's ``raw_noise_std``)."""
    inverse_depth: bool = False
    """Samples uniform in 1/depth instead of depth (Semantic-NeRF: in depth, between near and far)."""
    field: str = "mlp"
    """``mlp``: Semantic-NeRF's positional-encoding MLP (``width``, ``depth``, ``skip``, ``position_frequencies``);
    ``grid``: a multiresolution hash grid with small networks (Instant-NGP's; the ``grid_*`` options), the same
    outputs, sampling and losses (``+experiment=baselines/semantic_nerf_grid``; docs/families/semantic_nerf.md)."""
    grid_levels: int = 16
    """``field=grid``: resolution levels (Instant-NGP: 16)."""
    grid_features: int = 2
    """``field=grid``: values per table entry (Instant-NGP: 2)."""
    grid_table_log2: int = 16
    """``field=grid``: each level's hash table holds 2^this entries (Instant-NGP: 2^19, for scenes far larger than
    these)."""
    grid_base_resolution: float = 16.0
    """``field=grid``: cells per scaled unit of the coarsest level (scaled by ``position_scale``: 16 cells per 10 m)."""
    grid_finest_resolution: float = 1024.0
    """``field=grid``: cells per scaled unit of the finest level (1024 per 10 m: cells of 1 cm, about a pixel's
    footprint at 96 x 128 and 1-2 m)."""
    grid_width: int = 64
    """``field=grid``: hidden width of its density and colour networks (Instant-NGP: 64)."""
    lr: GridFieldRates = dataclasses.field(default_factory=GridFieldRates)  # (its option ``field`` hides the name)
    """Learning rates (``model.lr.<group>``): ``field`` (the MLP, or the grid's small networks) and ``grid`` (its
    tables)."""
