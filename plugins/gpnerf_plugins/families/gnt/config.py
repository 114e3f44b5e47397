"""Options of the ``gnt`` model family (``model=gnt``, the default): GP-NeRF's, at the paper's sizes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from gpnerf_core import ModelConfig, RayMarchingConfig, part
from gpnerf_plugins.families.rates import SourceViewRates


@dataclass
class SemanticFieldConfig:
    enabled: bool = True
    """Render the semantic-embedding field (off = GNT alone)."""
    joint_attention: bool = True
    """Semantic losses also train the transformers' attention (Table 4: False = frozen attention, ID 1)."""
    adaptor_relu: bool = False
    """ReLU after the 512->512 adaptor, as the released code (its teacher is signed, so off by default)."""


@dataclass
class GNTModelConfig(RayMarchingConfig):
    """GNT's view and ray transformers (``field_aggregator``, ``ray_aggregator``) over the ``feature_extractor``'s maps,
    GP-NeRF's semantic field on their attention, and the ``+head`` on the rendered map."""

    name: str = "gnt"
    """Registry name of this model family."""
    feature_extractor: Any = part("resunet_fpn")
    """Encodes source and target images: radiance maps for the transformers, semantic maps for the field and head."""
    field_aggregator: Any = part("gnt_view")
    """GNT's view transformer: attention over the source views per sample (FAT)."""
    ray_aggregator: Any = part("gnt_ray")
    """GNT's ray transformer: attention over a ray's samples (RAT)."""
    sampler: str = "uniform"
    """Samples of the fine pass: ``uniform`` (the coarse samples plus ``fine_samples`` drawn from the coarse weights,
    GNT's) or ``depth`` (only ``fine_samples`` samples, around the coarse pass's depth, or drawn from the coarse
    weights where that depth is uncertain: ``gpnerf_core.geometry.surface_depths``; fewer samples where the surfaces
    are). With ``+depth_source=<name>`` the depth comes from the source views instead: one pass, no coarse pass."""
    surface_spread: float = 2.0
    """``sampler=depth``: the fine samples span the coarse depth +- this many standard deviations of its weights
    (at least one coarse bin)."""
    surface_uncertainty: float = 0.2
    """``sampler=depth``: a ray whose weights' standard deviation exceeds this fraction of its depth is uncertain and
    gets its fine samples drawn from the coarse weights."""
    detach_source_semantics: bool = True
    """Rendered-feature losses do not train the extractor through the source views (released code)."""
    semantic_field: SemanticFieldConfig = field(default_factory=SemanticFieldConfig)
    fuse_rendered: bool = True
    """In training the head decodes the fused map (the teacher map with the rendered features in the rays' cells, the
    paper); False decodes the teacher map alone (the released code)."""
    checkpoint_blocks: bool = False
    """Activation checkpointing of the transformer blocks: recompute them in the backward pass (less memory)."""
    channels_last_maps: bool = True
    """Copy the detached source semantic maps channels-last where each is sampled at more points than it has pixels:
    ``grid_sample`` then reads each sample's channels contiguously (the same float32 values, about 2.7x faster at
    512 channels)."""
    compile: bool = False
    """``torch.compile`` the transformer block pairs and the semantic attention sums (compiled on first use)."""
    compile_backend: str = "inductor"
    """The ``torch.compile`` backend when ``compile`` is true (inductor: C++ on CPU, Triton on CUDA)."""
    lr: SourceViewRates = field(default_factory=SourceViewRates)
    """Learning rates (``model.lr.<group>``): ``feature_extractor``, ``transformer`` (the aggregators and the semantic
    adaptor), ``head``."""

    runtime_keys: ClassVar[tuple[str, ...]] = (
        *ModelConfig.runtime_keys, "checkpoint_blocks", "channels_last_maps", "compile", "compile_backend",
    )
