"""Building the ``semantic_3dgs`` family from its options and the configured head."""

from __future__ import annotations

import math

from gpnerf_core import RASTERIZER_BACKENDS, BudgetedStrategy, ConfigError, DefaultStrategy, ModelParts
from gpnerf_plugins.families.semantic_3dgs.config import Semantic3DGSConfig
from gpnerf_plugins.families.semantic_3dgs.model import Semantic3DGS

C = Semantic3DGSConfig
SCHEDULE_KEYS = ("schedule_steps", "densify_from", "densify_until", "densify_every", "opacity_reset_every",
                 "sh_degree_every")
DENSITY = {"default": DefaultStrategy, "budgeted": BudgetedStrategy}
"""``model.density`` -> the strategy (``gpnerf_core.geometry.gaussians.density``)."""


def _integer(key: str, value: object, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"model.{key}={value!r}: expected an integer >= {least}")
    return value


def _number(key: str, value: object, low: float, high: float, *, open_low: bool = True) -> float:
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    ok = ok and (low < value if open_low else low <= value) and value <= high
    if not ok:
        bound = "(" if open_low else "["
        raise ConfigError(f"model.{key}={value!r}: expected a finite number in {bound}{low:g}, {high:g}]")
    return float(value)


def build_semantic_3dgs(*, parts: ModelParts, sh_degree: int = C.sh_degree, feature_dim: int = C.feature_dim,
                        init_points: int = C.init_points, init_depth_stride: int = C.init_depth_stride,
                        init_opacity: float = C.init_opacity, max_gaussians: int = C.max_gaussians,
                        schedule_steps: int = C.schedule_steps, densify_from: int = C.densify_from,
                        densify_until: int = C.densify_until, densify_every: int = C.densify_every,
                        opacity_reset_every: int = C.opacity_reset_every, sh_degree_every: int = C.sh_degree_every,
                        densify_grad_threshold: float = C.densify_grad_threshold,
                        percent_dense: float = C.percent_dense, prune_opacity: float = C.prune_opacity,
                        prune_screen_radius: float = C.prune_screen_radius,
                        prune_world_scale: float = C.prune_world_scale, means_final_ratio: float = C.means_final_ratio,
                        background: float = C.background, rasterizer: str = C.rasterizer,
                        density: str = C.density) -> Semantic3DGS:
    """The family for the dataset's classes: a 1 x 1 convolution decodes the rendered features without a ``+head``,
    the head with one (it decodes ``feature_dim`` channels in one level)."""
    _integer("sh_degree", sh_degree, 0)
    if sh_degree > 3:
        raise ConfigError(f"model.sh_degree={sh_degree}: expected 0 to 3 (3D Gaussian splatting's degrees)")
    _integer("feature_dim", feature_dim, 1)
    _integer("init_points", init_points, 1)
    _integer("init_depth_stride", init_depth_stride, 1)
    _integer("max_gaussians", max_gaussians, 1)
    schedule = {key: _integer(key, value, 1) for key, value in zip(SCHEDULE_KEYS, (
        schedule_steps, densify_from, densify_until, densify_every, opacity_reset_every, sh_degree_every))}
    _number("init_opacity", init_opacity, 0.0, 1.0)
    if init_opacity >= 1.0:
        raise ConfigError(f"model.init_opacity={init_opacity!r}: expected a number in (0, 1)")
    if density not in DENSITY:
        raise ConfigError(f"model.density={density!r}: expected one of {', '.join(DENSITY)}")
    thresholds = dict(
        grad_threshold=_number("densify_grad_threshold", densify_grad_threshold, 0.0, math.inf),
        percent_dense=_number("percent_dense", percent_dense, 0.0, 1.0),
        prune_opacity=_number("prune_opacity", prune_opacity, 0.0, 1.0, open_low=False),
        prune_screen_radius=_number("prune_screen_radius", prune_screen_radius, 0.0, math.inf),
        prune_world_scale=_number("prune_world_scale", prune_world_scale, 0.0, math.inf),
        max_gaussians=max_gaussians,
        **{key: schedule[key] for key in SCHEDULE_KEYS if key != "sh_degree_every"},
    )
    strategy = DefaultStrategy(**thresholds) if density == "default" else BudgetedStrategy(**thresholds,
                                                                                          budget=max_gaussians)
    _number("means_final_ratio", means_final_ratio, 0.0, 1.0)
    _number("background", background, 0.0, 1.0, open_low=False)
    if rasterizer not in RASTERIZER_BACKENDS:
        raise ConfigError(f"model.rasterizer={rasterizer!r}: expected one of {', '.join(RASTERIZER_BACKENDS)}")
    head = parts.head(in_dim=feature_dim, in_levels=1) if parts.configured("head") else None
    return Semantic3DGS(head=head, num_classes=parts.num_classes, sh_degree=sh_degree, feature_dim=feature_dim,
                        init_points=init_points, init_depth_stride=init_depth_stride, init_opacity=init_opacity,
                        strategy=strategy, sh_degree_every=schedule["sh_degree_every"],
                        means_final_ratio=means_final_ratio, background=background, rasterizer=rasterizer)
