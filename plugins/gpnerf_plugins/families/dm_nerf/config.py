"""Options of the ``dm_nerf`` family (``+experiment=baselines/dm_nerf``): DM-NeRF's, with the widths, depths and sample
counts this machine can train (each official value in the field's docstring)."""

from __future__ import annotations

from dataclasses import dataclass, field

from gpnerf_core import RayMarchingConfig
from gpnerf_plugins.families.rates import FieldRates


@dataclass
class DMNeRFConfig(RayMarchingConfig):
    """One scene's radiance field with DM-NeRF's object field on its detached trunk features: ``slots + 1`` object
    logits per sample, composited with detached weights, a sigmoid per slot (docs/families/dm_nerf.md)."""

    name: str = "dm_nerf"
    """Registry name of this model family."""
    slots: int = 16
    """Object slots K (the last of the K + 1 outputs is "empty"); at least the instance ids of any training frame
    (DM-NeRF: the scene's instance count, 59-93 on Replica)."""
    coarse_samples: int = 32
    """Stratified samples per ray of the coarse network, uniform in depth (DM-NeRF: 64)."""
    fine_samples: int = 32
    """Importance samples added for the fine network (DM-NeRF: 128; 0 = the coarse network alone)."""
    num_source_views: int = 0
    """None: a per-scene model renders from its own parameters."""
    width: int = 128
    """Width of the trunk (DM-NeRF: 256)."""
    depth: int = 6
    """Layers of the trunk (DM-NeRF: 8)."""
    skip: int = 4
    """The encoded position is concatenated to the trunk after layer ``skip`` (0-based; NeRF's 4)."""
    position_scale: float = 1.0
    """Positions are multiplied by this before the encoding (DM-NeRF: no scaling)."""
    position_frequencies: int = 10
    """Octaves of the position encoding (10: 63 channels)."""
    direction_frequencies: int = 4
    """Octaves of the view-direction encoding (4: 27 channels)."""
    density_noise: float = 1.0
    """Standard deviation of the noise added to the raw density in training (NeRF's ``raw_noise_std``, as Semantic-NeRF
    trains)."""
    inverse_depth: bool = False
    """Samples uniform in 1/depth instead of depth (DM-NeRF: in depth)."""
    lr: FieldRates = field(default_factory=FieldRates)
    """Learning rates (``model.lr.field``: the NeRF and object fields; DM-NeRF: 5e-4)."""
