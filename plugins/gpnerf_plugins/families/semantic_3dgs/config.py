"""Options of the ``semantic_3dgs`` family (``+experiment=baselines/semantic_3dgs``): 3D Gaussian splatting's official
defaults (``graphdeco-inria/gaussian-splatting``, ``arguments/__init__.py``, commit 01f0874) with the semantic feature
of Feature 3DGS and Gaussian Grouping; each official value in the field's docstring."""

from __future__ import annotations

from dataclasses import dataclass, field

from gpnerf_core import GaussianRates, GaussianSceneConfig


@dataclass
class Semantic3DGSLearningRates(GaussianRates):
    """The family's learning-rate groups (``model.lr.<group>``): 3DGS's Adam rates (``GaussianRates``), and the semantic
    feature's and the classifier's or the ``+head``'s."""

    features: float = 2.5e-3
    """The semantic feature of each Gaussian (Gaussian Grouping: its identity encoding at ``feature_lr`` 2.5e-3)."""
    head: float = 5e-5
    """The 1 x 1 classifier or the ``+head`` (GP-NeRF's rate for a head)."""
    feature_field: float = 2.5e-3
    """Each Gaussian's feature-field vector (``+feature_provider``; the semantic feature's rate, Gaussian Grouping's
    ``feature_lr``)."""


@dataclass
class Semantic3DGSConfig(GaussianSceneConfig):
    """One scene as 3D Gaussians (Kerbl et al., SIGGRAPH 2023) with a semantic feature each (Feature 3DGS, CVPR 2024;
    Gaussian Grouping, ECCV 2024), started from the scene's sparse points or depth, densified and pruned while it
    trains, rasterized (docs/families/semantic_3dgs.md); 3DGS's options are ``GaussianSceneConfig``'s. The schedule's
    step numbers are the official ones for ``schedule_steps`` steps and are scaled to ``train.steps``."""

    name: str = "semantic_3dgs"
    """Registry name of this model family."""
    feature_dim: int = 16
    """Channels of each Gaussian's semantic feature, rasterized beside the colour and decoded per pixel by a 1 x 1
    convolution to the classes, or by the ``+head`` (Gaussian Grouping: a 16-channel identity encoding)."""
    feature_levels: int = 1
    """Equal channel blocks of each Gaussian's semantic feature as the ``+head`` reads them, finest first (a divisor of
    ``feature_dim``); a start from a generalizable model takes its extractor's ``semantic_levels``
    (``gpnerf_core.start_overrides``)."""
    feature_stride: int = 1
    """Pixels per cell of the rendered feature map the decoder reads: 1 renders it with the colour in one
    rasterization; above 1 it is rasterized again on that stride's grid and decoded to the full image. A start from a
    generalizable model takes its head's stride (the head was trained on maps at that resolution)."""
    lr: Semantic3DGSLearningRates = field(default_factory=Semantic3DGSLearningRates)
    """Learning rates (``model.lr.<group>``)."""
