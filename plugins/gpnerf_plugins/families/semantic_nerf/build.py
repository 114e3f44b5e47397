"""Building the ``semantic_nerf`` family from its options: it builds no parts (no extractor, no head)."""

from __future__ import annotations

from gpnerf_core import ConfigError, ModelParts
from gpnerf_plugins.families.semantic_nerf.config import SemanticNeRFConfig
from gpnerf_plugins.families.semantic_nerf.model import SemanticNeRF

C = SemanticNeRFConfig


def build_semantic_nerf(*, parts: ModelParts, coarse_samples: int = C.coarse_samples,
                        fine_samples: int = C.fine_samples, width: int = C.width, depth: int = C.depth,
                        skip: int = C.skip, position_scale: float = C.position_scale,
                        position_frequencies: int = C.position_frequencies,
                        direction_frequencies: int = C.direction_frequencies, density_noise: float = C.density_noise,
                        inverse_depth: bool = C.inverse_depth, field: str = C.field, grid_levels: int = C.grid_levels,
                        grid_features: int = C.grid_features, grid_table_log2: int = C.grid_table_log2,
                        grid_base_resolution: float = C.grid_base_resolution,
                        grid_finest_resolution: float = C.grid_finest_resolution,
                        grid_width: int = C.grid_width) -> SemanticNeRF:
    """Semantic-NeRF for the dataset's classes; a configured ``+head`` is refused (it renders class scores itself)."""
    if parts.configured("head"):
        raise ConfigError(f"model=semantic_nerf renders class scores per sample (label rendering) and decodes no "
                          f"feature map: drop +head={parts.name('head')}")
    return SemanticNeRF(num_classes=parts.num_classes, coarse_samples=coarse_samples, fine_samples=fine_samples,
                        width=width, depth=depth, skip=skip, position_scale=position_scale,
                        position_frequencies=position_frequencies, direction_frequencies=direction_frequencies,
                        density_noise=density_noise, inverse_depth=inverse_depth, field=field, grid_levels=grid_levels,
                        grid_features=grid_features, grid_table_log2=grid_table_log2,
                        grid_base_resolution=grid_base_resolution, grid_finest_resolution=grid_finest_resolution,
                        grid_width=grid_width)
