"""Options of the ``semantic_3dgs`` family (``+experiment=baselines/semantic_3dgs``): 3D Gaussian splatting's official
defaults (``graphdeco-inria/gaussian-splatting``, ``arguments/__init__.py``, commit 01f0874) with the semantic feature
of Feature 3DGS and Gaussian Grouping; each official value in the field's docstring."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from gpnerf_core import ModelConfig


@dataclass
class Semantic3DGSLearningRates:
    """The family's learning-rate groups (``model.lr.<group>``): 3DGS's Adam rates, and the semantic classifier's or the
    ``+head``'s."""

    means: float = 1.6e-4
    """Centres, per metre of the scene's extent (3DGS: ``position_lr_init`` 1.6e-4 x the cameras' extent), decayed
    log-linearly to ``means_final_ratio`` of it over the training steps."""
    harmonics: float = 2.5e-3
    """The degree-0 colour coefficient (3DGS: ``feature_lr`` 2.5e-3)."""
    harmonics_rest: float = 1.25e-4
    """The higher-degree coefficients (3DGS: ``feature_lr / 20``)."""
    opacities: float = 0.05
    """Opacity logits (3DGS: ``opacity_lr`` 0.05)."""
    scales: float = 1.0e-3
    """Log scales (3DGS: ``scaling_lr`` 1e-3)."""
    rotations: float = 1.0e-3
    """Quaternions (3DGS: ``rotation_lr`` 1e-3)."""
    features: float = 2.5e-3
    """The semantic feature of each Gaussian (Gaussian Grouping: its identity encoding at ``feature_lr`` 2.5e-3)."""
    head: float = 5e-5
    """The 1 x 1 classifier or the ``+head`` (GP-NeRF's rate for a head)."""


@dataclass
class Semantic3DGSConfig(ModelConfig):
    """One scene as 3D Gaussians (Kerbl et al., SIGGRAPH 2023) with a semantic feature each (Feature 3DGS, CVPR 2024;
    Gaussian Grouping, ECCV 2024), started from the scene's sparse points or depth, densified and pruned while it
    trains, rasterized (docs/families/semantic_3dgs.md). The schedule's step numbers are the official ones for
    ``schedule_steps`` steps and are scaled to ``train.steps``."""

    name: str = "semantic_3dgs"
    """Registry name of this model family."""
    num_source_views: int = 0
    """None: a per-scene model renders from its own parameters."""
    sh_degree: int = 3
    """Largest degree of each Gaussian's spherical-harmonic colour, reached one degree at a time (3DGS: 3)."""
    feature_dim: int = 16
    """Channels of each Gaussian's semantic feature, rasterized beside the colour and decoded per pixel by a 1 x 1
    convolution to the classes, or by the ``+head`` (Gaussian Grouping: a 16-channel identity encoding)."""
    init_points: int = 20000
    """At most this many Gaussians to start from, a random subset of the scene's sparse points (3DGS: all of
    COLMAP's), or of its training frames' depth back-projected where it has no sparse points."""
    init_depth_stride: int = 2
    """Back-projected depth: every ``init_depth_stride``-th pixel of each training frame (before the subset)."""
    init_opacity: float = 0.1
    """Opacity of every starting Gaussian (3DGS: 0.1)."""
    max_gaussians: int = 200000
    """Densification stops adding Gaussians at this count (said once in the run's log); with ``density=budgeted`` the
    budget the count never exceeds."""
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
    lr: Semantic3DGSLearningRates = field(default_factory=Semantic3DGSLearningRates)
    """Learning rates (``model.lr.<group>``)."""

    runtime_keys: ClassVar[tuple[str, ...]] = (*ModelConfig.runtime_keys, "rasterizer", "max_gaussians")
