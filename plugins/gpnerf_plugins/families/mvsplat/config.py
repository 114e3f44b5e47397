"""Options of the ``mvsplat`` model family (``model=mvsplat``), at CPU scale (each official value in the field's
docstring; ``model.py`` says why each differs)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from gpnerf_core import ModelConfig, fractions, part, size_knob


@dataclass
class MVSplatLearningRates:
    """The family's learning-rate groups (``model.lr.<group>``)."""

    feature_extractor: float = 5e-3
    """The extractor (``model.feature_extractor``; GP-NeRF's rate for it)."""
    mvsplat: float = 2.0e-4
    """The multi-view transformer, the cost-volume and depth networks and the Gaussian head (MVSplat: Adam 2e-4)."""
    head: float = 5e-5
    """The ``+head`` (GP-NeRF's rate for it)."""


@dataclass
class MVSplatConfig(ModelConfig):
    """Feed-forward 3D Gaussians (MVSplat, Chen et al., ECCV 2024): the source views' features with cross-view
    attention, a plane-sweep cost volume per view, depth by soft-argmin and refinement, one Gaussian per source pixel,
    rasterized into the target (docs/families/mvsplat.md)."""

    name: str = "mvsplat"
    """Registry name of this model family."""
    feature_extractor: Any = part("resunet_fpn")
    """Encodes each source view: its 1/4 radiance map is MVSplat's CNN features, its semantic maps what each Gaussian
    carries for a ``+head``."""
    num_source_views: int = 2
    """Source views whose pixels become Gaussians (MVSplat: 2 context views; any count >= 2 works)."""
    feature_dim: int = size_knob(64, "matching width", fractions(2, 4, 0.75, 0.5))
    """Channels of the multi-view transformer and the cost volume's features (MVSplat: ``d_feature`` 128)."""
    transformer_layers: int = 2
    """Blocks of self- then cross-view attention over the 1/4 maps (MVSplat: 6)."""
    attention_splits: int = 2
    """Each 1/4 map is cut into splits x splits windows for attention, shifted by half a window every other block
    (MVSplat: ``multiview_trans_attn_split`` 2)."""
    depth_candidates: int = size_knob(32, "depth candidates", fractions(2, 4, 0.75, 0.5))
    """Depths of the cost volume, uniform in inverse depth between near and far (MVSplat: ``num_depth_candidates``
    32; 128 for RE10K)."""
    cost_unet_dim: int = 32
    """Channels of the 2D U-Net refining the cost volume (MVSplat: ``costvolume_unet_feat_dim`` 128)."""
    depth_unet_dim: int = 32
    """Channels of the full-resolution depth-refinement U-Net (MVSplat: ``depth_unet_feat_dim`` 64)."""
    unet_levels: int = 3
    """Resolutions of both U-Nets (MVSplat: ``channel_mult`` [1, 1, 1], three)."""
    sh_degree: int = 2
    """Degree of each Gaussian's spherical-harmonic colour, damped per degree at the start (MVSplat: 4)."""
    scale_min: float = 0.5
    """Smallest scale of a Gaussian, in MVSplat's units: this x depth x 0.1 (1/fx + 1/fy), i.e. 0.1 pixel footprint
    at 0.5 (MVSplat: ``gaussian_scale_min`` 0.5)."""
    scale_max: float = 15.0
    """Largest scale, in the same units (MVSplat: ``gaussian_scale_max`` 15)."""
    label_rendering: bool = True
    """Without a ``+head``: each Gaussian also carries K class scores, rasterized and scored per pixel (off: colour and
    depth only, MVSplat itself). With a head each Gaussian carries its source pixel's semantic feature instead."""
    background: float = 0.0
    """Colour where no Gaussian covers a pixel (MVSplat: the dataset's, black for RE10K)."""
    rasterizer: str = "auto"
    """Rasterizer backend: ``auto`` (gsplat on CUDA where installed, numba on CPU, else torch), ``numba``, ``torch``
    or ``gsplat`` (docs/rasterizer.md)."""
    lr: MVSplatLearningRates = field(default_factory=MVSplatLearningRates)
    """Learning rates (``model.lr.<group>``): ``feature_extractor``, ``mvsplat``, ``head``."""

    runtime_keys: ClassVar[tuple[str, ...]] = (*ModelConfig.runtime_keys, "rasterizer")
