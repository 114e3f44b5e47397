"""Options of the ``mvsnerf`` model family (``model=mvsnerf``), at CPU scale (``model.py`` lists the official sizes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from gpnerf_core import ModelConfig, RayMarchingConfig, part
from gpnerf_plugins.families.rates import SourceViewRates


@dataclass
class MVSNeRFConfig(RayMarchingConfig):
    """MVSNeRF + semantic head: a plane-sweep cost volume in the first source view's frustum, regularised by a 3D U-Net
    into an encoding volume, read per sample by a modulated MLP that renders colour, density and class scores (with a
    ``+head``: semantic features the head decodes, ``+experiment=baselines/mvsnerf_unet``)."""

    name: str = "mvsnerf"
    """Registry name of this model family."""
    feature_extractor: Any = part("mvsnet")
    """Encodes the source views: MVSNeRF's FeatureNet (``mvsnet``); with a ``+head``, an extractor that makes semantic
    maps (``model/feature_extractor=resunet_fpn``, ``+experiment=baselines/mvsnerf_unet``)."""
    coarse_samples: int = 48
    """Stratified samples per ray, uniform in depth (MVSNeRF: 128)."""
    fine_samples: int = 0
    """Importance samples of a second pass through the same network (MVSNeRF: N_importance 0, one pass)."""
    num_source_views: int = 3
    """Source views per target; the first is the reference view whose frustum holds the cost volume (MVSNeRF: 3)."""
    volume_views: int = 3
    """Views the network is built for: the cost volume's RGB channels (3 per view) and the MLP's per-view colour and
    in-image flag (4 per view). Keep it equal to ``num_source_views`` (the baseline experiment ties them); a target
    given more views uses the first ``volume_views``, one given fewer gets zeros for the missing ones."""
    num_planes: int = 48
    """D: depth planes of the cost volume between near and far, a multiple of 8 (MVSNeRF: 128)."""
    inverse_depth: bool = False
    """Planes, samples and the volume's depth coordinate uniform in 1/depth (MVSNeRF's ``lindisp``; off in its runs)."""
    pad: list[int] = field(default_factory=lambda: [0, 0])
    """Cells of the 1/4 map added to the reference frustum on each side, [rows, columns], at least: MVSNeRF's ``pad``
    (24 by default there, for DTU's 128 x 160 map) widens the volume past the reference image. The 3D U-Net needs
    sides that are multiples of 8, so each is raised to the fewest cells that make it one (with [0, 0]: none at
    96 x 128, 2 columns at 32 x 48, 2 rows at 240 x 320); image sides must be multiples of 8 pixels."""
    sampler: str = "uniform"
    """``uniform``: MVSNeRF's samples (and an importance pass with ``fine_samples``). ``depth`` (with
    ``+depth_source=<name>``, which it needs here): one pass on ``fine_samples`` samples around the source views' depth
    of each ray, or spread by its belief where that depth is uncertain (``gpnerf_core.SurfaceSampling``;
    docs/rendering.md)."""
    surface_spread: float = 2.0
    """``sampler=depth``: the samples span the depth +- this many standard deviations of the belief."""
    surface_uncertainty: float = 0.2
    """``sampler=depth``: a ray whose belief's standard deviation exceeds this fraction of its depth gets its samples
    drawn from the belief."""
    width: int = 128
    """Width of the MLP trunk (MVSNeRF: 128, 6 layers); the colour branch has half of it, as the semantic branch."""
    label_rendering: bool = True
    """Render class scores with the semantic branch (off: colour and depth only, MVSNeRF itself); with a ``+head`` the
    branch renders the head's input features whatever this is."""
    lr: SourceViewRates = field(default_factory=SourceViewRates)
    """Learning rates (``model.lr.<group>``): ``feature_extractor``, ``transformer`` (the 3D U-Net and the MLP),
    ``head``."""

    runtime_keys: ClassVar[tuple[str, ...]] = ModelConfig.runtime_keys
