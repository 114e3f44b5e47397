"""Building the ``mvsplat`` family from its options and the configured feature extractor and head."""

from __future__ import annotations

import math

from gpnerf_core import RASTERIZER_BACKENDS, ConfigError, ModelParts
from gpnerf_plugins.families.mvsplat.config import MVSplatConfig
from gpnerf_plugins.families.mvsplat.model import MVSplat


MAX_DEPTH_CANDIDATES = 1024
"""The most depth candidates ``model.depth_candidates`` takes (MVSplat: 32, 128 for RE10K): the layers over the
candidates grow with their square (``depth_layer_weights``), about 39M weights at 1024."""


def depth_layer_weights(candidates: int, feature_dim: int, cost_dim: int) -> int:
    """The weights of ``DepthPredictor``'s layers whose size depends on the D = ``candidates`` depth candidates (the
    cost volume's input and output convolutions, its residual and the 3 x 3 depth head, about 37 D^2)."""
    d, volume_in = candidates, candidates + feature_dim
    cost_refine = volume_in * cost_dim * 9 + cost_dim + cost_dim * d * 9 + d
    cost_residual = volume_in * d + d
    depth_head = d * 2 * d * 9 + 2 * d + 2 * d * d * 9 + d
    return cost_refine + cost_residual + depth_head


def _check(feature_dim: int, transformer_layers: int, attention_splits: int, depth_candidates: int, cost_unet_dim: int,
           depth_unet_dim: int, unet_levels: int, scale_min: float, scale_max: float, background: float,
           rasterizer: str) -> None:
    counts = {"feature_dim": (feature_dim, 2), "transformer_layers": (transformer_layers, 0),
              "attention_splits": (attention_splits, 1), "depth_candidates": (depth_candidates, 2),
              "cost_unet_dim": (cost_unet_dim, 1), "depth_unet_dim": (depth_unet_dim, 1), "unet_levels": (unet_levels, 1)}
    for key, (value, least) in counts.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ConfigError(f"model.{key}={value!r}: expected an integer >= {least}")
    if not depth_candidates <= MAX_DEPTH_CANDIDATES:
        weights = depth_layer_weights(depth_candidates, feature_dim, cost_unet_dim)
        raise ConfigError(f"model.depth_candidates={depth_candidates}: expected 2 to {MAX_DEPTH_CANDIDATES}; the layers "
                          f"over the candidates alone would hold {weights:.2g} weights, about {weights * 4 / 1e9:.3g} GB "
                          f"in float32 ({weights * 16 / 1e9:.3g} GB training, with gradients and Adam's two moments)")
    if feature_dim % 2:
        raise ConfigError(f"model.feature_dim={feature_dim}: expected an even number (half the position embedding is "
                          "for rows, half for columns)")
    if not (math.isfinite(scale_min) and math.isfinite(scale_max) and 0 < scale_min < scale_max):
        raise ConfigError(f"model.scale_min={scale_min}, model.scale_max={scale_max}: expected finite 0 < min < max")
    if not (math.isfinite(background) and 0 <= background <= 1):
        raise ConfigError(f"model.background={background}: expected a colour value in [0, 1]")
    if rasterizer not in RASTERIZER_BACKENDS:
        raise ConfigError(f"model.rasterizer={rasterizer!r}: expected one of {', '.join(RASTERIZER_BACKENDS)}")


MAX_SH_DEGREE = 4
"""The highest colour degree the rasterizing families evaluate (``gpnerf_core.sh_colours``; MVSplat's own)."""


def _check_sh_degree(sh_degree: object) -> None:
    if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise ConfigError(f"model.sh_degree={sh_degree!r}: expected an integer in [0, {MAX_SH_DEGREE}] (the colour's "
                          "spherical-harmonic degree; MVSplat's is 4)")


def build_mvsplat(
    *,
    parts: ModelParts,
    feature_dim: int = MVSplatConfig.feature_dim,
    transformer_layers: int = MVSplatConfig.transformer_layers,
    attention_splits: int = MVSplatConfig.attention_splits,
    depth_candidates: int = MVSplatConfig.depth_candidates,
    cost_unet_dim: int = MVSplatConfig.cost_unet_dim,
    depth_unet_dim: int = MVSplatConfig.depth_unet_dim,
    unet_levels: int = MVSplatConfig.unet_levels,
    sh_degree: int = MVSplatConfig.sh_degree,
    scale_min: float = MVSplatConfig.scale_min,
    scale_max: float = MVSplatConfig.scale_max,
    label_rendering: bool = MVSplatConfig.label_rendering,
    background: float = MVSplatConfig.background,
    rasterizer: str = MVSplatConfig.rasterizer,
) -> MVSplat:
    """The extractor the config selects (its 1/4 radiance maps are MVSplat's CNN features) and the family's own
    networks. Without a ``+head`` each Gaussian carries class scores (label rendering); with one it carries the
    extractor's semantic feature at its source pixel, which needs an extractor with semantic maps (refused in one line
    otherwise). With ``+feature_provider`` each Gaussian also carries the provider's feature at its source pixel
    (``parts.feature_field()``)."""
    _check_sh_degree(sh_degree)
    _check(feature_dim, transformer_layers, attention_splits, depth_candidates, cost_unet_dim, depth_unet_dim,
           unet_levels, float(scale_min), float(scale_max), float(background), rasterizer)
    extractor = parts.build("feature_extractor")
    head = parts.semantic_head(extractor, "mvsplat", decodes="the Gaussians' semantic features")
    return MVSplat(extractor=extractor, head=head, num_classes=parts.num_classes if label_rendering else 0,
                   feature_dim=feature_dim, transformer_layers=transformer_layers, attention_splits=attention_splits,
                   depth_candidates=depth_candidates, cost_unet_dim=cost_unet_dim, depth_unet_dim=depth_unet_dim,
                   unet_levels=unet_levels, sh_degree=sh_degree, scale_min=scale_min, scale_max=scale_max,
                   background=background, rasterizer=rasterizer, feature_field=parts.feature_field())
