"""The options every per-scene Gaussian family shares (``GaussianSceneConfig``: 3D Gaussian splatting's start, schedule
and density control, official defaults from ``graphdeco-inria/gaussian-splatting`` ``arguments/__init__.py`` at
01f0874) and ``gaussian_setup``, which checks them and makes the configured density strategy.

A family's config subclasses ``GaussianSceneConfig`` and adds its own fields (its channels, its decoder, its learning
rates: a subclass of ``GaussianRates``); its factory takes its own fields by name and hands the rest to
``gaussian_setup``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

from gpnerf_core.config.schema import ModelConfig
from gpnerf_core.errors import ConfigError
from gpnerf_core.registry.declarations import fractions, size_knob
from gpnerf_core.geometry.gaussians.density import BudgetedStrategy, DefaultStrategy
from gpnerf_core.geometry.gaussians.rasterizer import RASTERIZER_BACKENDS

DENSITY: dict[str, type[DefaultStrategy]] = {"default": DefaultStrategy, "budgeted": BudgetedStrategy}
"""``model.density`` -> the strategy (``gpnerf_core.geometry.gaussians.density``)."""
SCHEDULE_KEYS = ("schedule_steps", "densify_from", "densify_until", "densify_every", "opacity_reset_every",
                 "sh_degree_every")


@dataclass
class GaussianRates:
    """3D Gaussian splatting's Adam rates for the Gaussians' own groups (``model.lr.<group>``); a family's ``lr``
    section subclasses it and adds its channels' and its decoder's groups."""

    means: float = 1.6e-4
    """Centres, per metre of the scene's extent (3DGS: ``position_lr_init`` 1.6e-4 x the cameras' extent), decayed
    log-linearly to ``means_final_ratio`` of it over the training steps."""
    harmonics: float = 2.5e-3
    """The degree-0 colour coefficient (3DGS: ``feature_lr`` 2.5e-3)."""
    harmonics_rest: float = 1.25e-4
    """The higher-degree coefficients (3DGS: ``feature_lr / 20``)."""
    opacities: float = 0.05
    """Opacity logits (3DGS: ``opacity_lr`` 0.05)."""
    scales: float = 5.0e-3
    """Log scales (3DGS: ``scaling_lr`` 5e-3, as Feature 3DGS and Gaussian Grouping; 1e-3 before 2026-12-06)."""
    rotations: float = 1.0e-3
    """Quaternions (3DGS: ``rotation_lr`` 1e-3)."""


@dataclass
class GaussianSceneConfig(ModelConfig):
    """One scene as 3D Gaussians (Kerbl et al., SIGGRAPH 2023), started from the scene's sparse points or depth,
    densified and pruned while it trains, rasterized. The schedule's step numbers are the official ones for
    ``schedule_steps`` steps and are scaled to ``train.steps``."""

    num_source_views: int = 0
    """None: a per-scene model renders from its own parameters."""
    sh_degree: int = 3
    """Largest degree of each Gaussian's spherical-harmonic colour, reached one degree at a time (3DGS: 3)."""
    init_points: int = 20000
    """At most this many Gaussians to start from, a random subset of the scene's sparse points (3DGS: all of
    COLMAP's), or of its training frames' depth back-projected where it has no sparse points."""
    init_depth_stride: int = 2
    """Back-projected depth: every ``init_depth_stride``-th pixel of each training frame (before the subset)."""
    init_opacity: float = 0.1
    """Opacity of every starting Gaussian (3DGS: 0.1)."""
    max_gaussians: int = size_knob(200000, "Gaussians", fractions(1000, 1000, 0.5, 0.25, 0.125))
    """Densification stops adding Gaussians at this count (said once in the run's log); with ``density=budgeted`` the
    budget the count never exceeds. ``size``'s knob for a Gaussian family: it tries a half, a quarter and an eighth."""
    density: str = "default"
    """Density control (``gpnerf_core.geometry.gaussians.density``): ``default`` (3DGS's official schedule,
    ``DefaultStrategy``) or ``budgeted`` (``BudgetedStrategy``: the same schedule, the count rising linearly to
    ``max_gaussians`` and never past it, the largest gradients growing first)."""
    schedule_steps: int = 30000
    """Length of the official schedule the step numbers below belong to (3DGS: 30k iterations); each is scaled by
    ``train.steps / schedule_steps`` (set ``schedule_steps`` to ``train.steps`` to run them as written)."""
    densify_from: int = 500
    """First step of densification (3DGS: ``densify_from_iter`` 500)."""
    densify_until: int = 15000
    """Densification stops at this step (3DGS: ``densify_until_iter`` 15k)."""
    densify_every: int = 100
    """Steps between densifications (3DGS: ``densification_interval`` 100)."""
    opacity_reset_every: int = 3000
    """Every this many steps every opacity is capped at 0.01 (3DGS: ``opacity_reset_interval`` 3000)."""
    sh_degree_every: int = 1000
    """The colour's degree rises by one every this many steps (3DGS: 1000)."""
    densify_grad_threshold: float = 2.0e-4
    """A Gaussian whose mean view-space positional gradient (per unit of normalised device coordinates) reaches this
    is cloned or split (3DGS: ``densify_grad_threshold`` 2e-4)."""
    percent_dense: float = 0.01
    """Cloned if its largest scale is at most this fraction of the scene's extent, split otherwise (3DGS: 0.01)."""
    prune_opacity: float = 0.005
    """Pruned below this opacity (3DGS: 0.005)."""
    prune_screen_radius: float = 20.0
    """After the first opacity reset, pruned if its footprint radius reached this many pixels (3DGS: 20)."""
    prune_world_scale: float = 0.1
    """After the first opacity reset, pruned if its largest scale exceeds this fraction of the extent (3DGS: 0.1)."""
    means_final_ratio: float = 0.01
    """The centres' rate decays to this fraction of ``lr.means`` at the last step (3DGS: 1.6e-6 / 1.6e-4)."""
    background: float = 0.0
    """Colour where no Gaussian covers a pixel (3DGS: black unless ``--white_background``)."""
    rasterizer: str = "auto"
    """Rasterizer backend: ``auto`` (gsplat on CUDA where installed, numba on CPU, else torch), ``numba``, ``torch``
    or ``gsplat`` (docs/rasterizer.md)."""

    runtime_keys: ClassVar[tuple[str, ...]] = (*ModelConfig.runtime_keys, "rasterizer", "max_gaussians")


@dataclass(frozen=True)
class GaussianSetup:
    """``GaussianSceneConfig``'s options, checked, as ``GaussianFamily`` takes them: the density ``strategy`` at its
    official step numbers (``DefaultStrategy`` or ``BudgetedStrategy``) and the rest by their config names."""

    sh_degree: int
    init_points: int
    init_depth_stride: int
    init_opacity: float
    sh_degree_every: int
    means_final_ratio: float
    background: float
    rasterizer: str
    strategy: DefaultStrategy


def _integer(key: str, value: object, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"model.{key}={value!r}: expected an integer >= {least}")
    return value


def _number(key: str, value: object, low: float, high: float, *, open_low: bool = True, open_high: bool = False,
            why: str = "") -> float:
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    ok = ok and (low < value if open_low else low <= value) and (value < high if open_high else value <= high)
    if not ok:
        left, right = "(" if open_low else "[", ")" if open_high else "]"
        raise ConfigError(f"model.{key}={value!r}: expected a finite number in {left}{low:g}, {high:g}{right}{why}")
    return float(value)


def gaussian_setup(options: Mapping[str, Any]) -> GaussianSetup:
    """``GaussianSceneConfig``'s fields (``options``: a factory's keyword arguments besides its own; a field missing
    takes its default) checked, each bad value a one-line ``ConfigError`` naming ``model.<key>``, and the strategy
    made. A field the config does not have is refused naming it."""
    known = {f.name: f.default for f in dataclasses.fields(GaussianSceneConfig)}
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ConfigError(f"model.{unknown[0]}: not an option of a per-scene Gaussian family (GaussianSceneConfig)")
    o = {**known, **options}
    degree = o["sh_degree"]
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise ConfigError(f"model.sh_degree={degree!r}: expected an integer in [0, 3] (3D Gaussian splatting's "
                          "degrees)")
    for key in ("init_points", "init_depth_stride", "max_gaussians", *SCHEDULE_KEYS):
        _integer(key, o[key], 1)
    _number("init_opacity", o["init_opacity"], 0.0, 1.0, open_high=True,
            why=" (stored as its logit, infinite at 0 and 1; 3DGS: 0.1)")
    if o["density"] not in DENSITY:
        raise ConfigError(f"model.density={o['density']!r}: expected one of {', '.join(DENSITY)}")
    thresholds = dict(
        grad_threshold=_number("densify_grad_threshold", o["densify_grad_threshold"], 0.0, math.inf),
        percent_dense=_number("percent_dense", o["percent_dense"], 0.0, 1.0),
        prune_opacity=_number("prune_opacity", o["prune_opacity"], 0.0, 1.0, open_low=False, open_high=True,
                              why=" (Gaussians whose opacity is below it are pruned: 1 prunes every Gaussian; "
                                  "3DGS: 0.005)"),
        prune_screen_radius=_number("prune_screen_radius", o["prune_screen_radius"], 0.0, math.inf),
        prune_world_scale=_number("prune_world_scale", o["prune_world_scale"], 0.0, math.inf),
        max_gaussians=o["max_gaussians"],
        **{key: o[key] for key in SCHEDULE_KEYS if key != "sh_degree_every"},
    )
    budget = {"budget": o["max_gaussians"]} if o["density"] == "budgeted" else {}
    strategy = DENSITY[o["density"]](**thresholds, **budget)
    _number("means_final_ratio", o["means_final_ratio"], 0.0, 1.0)
    _number("background", o["background"], 0.0, 1.0, open_low=False)
    if o["rasterizer"] not in RASTERIZER_BACKENDS:
        raise ConfigError(f"model.rasterizer={o['rasterizer']!r}: expected one of {', '.join(RASTERIZER_BACKENDS)}")
    return GaussianSetup(sh_degree=o["sh_degree"], init_points=o["init_points"],
                         init_depth_stride=o["init_depth_stride"], init_opacity=o["init_opacity"],
                         sh_degree_every=o["sh_degree_every"], means_final_ratio=o["means_final_ratio"],
                         background=o["background"], rasterizer=o["rasterizer"], strategy=strategy)
