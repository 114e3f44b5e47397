"""Options of ``model=gaussian_grouping``: 3D Gaussian splatting's (``GaussianSceneConfig``) and Gaussian Grouping's
own, with the official values (``lkeab/gaussian-grouping@0ab60af``) in each field's docstring."""

from __future__ import annotations

from dataclasses import dataclass, field

from gpnerf_core import GaussianRates, GaussianSceneConfig


@dataclass
class GroupingRates(GaussianRates):
    """Adam rates (``model.lr.<group>``): 3DGS's for the Gaussians, and Gaussian Grouping's two."""

    identity: float = 2.5e-3
    """Each Gaussian's identity encoding (``feature_lr`` 2.5e-3)."""
    classifier: float = 5.0e-4
    """The 1 x 1 identity classifier (its own Adam at 5e-4, ``train.py``)."""


@dataclass
class GroupingWeights:
    """Weights of the family's own loss terms (``model.loss_weights.<term>``)."""

    identity: float = 1.0
    """2D identity loss: cross-entropy of the classified identity map against the mask ids, over ln K (weight 1)."""
    identity_3d: float = 2.0
    """3D regulariser: KL between each sampled Gaussian's identity distribution and its k nearest (``reg3d_lambda_val``
    2)."""


@dataclass
class GaussianGroupingConfig(GaussianSceneConfig):
    """Gaussian Grouping (Ye et al., ECCV 2024): 3D Gaussians with an identity encoding each, rasterized beside the
    colour, classified per pixel into mask ids; a 3D k-nearest-neighbour regulariser keeps neighbours' identities alike.
    The schedule's steps are the official ones for ``schedule_steps`` steps, scaled to ``train.steps``."""

    name: str = "gaussian_grouping"
    """Registry name of this model family."""
    identity_dim: int = 16
    """Channels of each Gaussian's identity encoding (``NUM_OBJECTS`` 16 in its rasterizer)."""
    slots: int = 16
    """Identity classes: mask ids 0 to ``slots - 1`` (``num_classes`` 256 in the shipped config; ids must stay below
    it); the classifier has one output more, the core's "no instance" channel, which no mask id trains."""
    densify_until: int = 10000
    """Densification stops at this step (Gaussian Grouping: 10k; 3DGS: 15k)."""
    reg3d_every: int = 5
    """The 3D regulariser runs every this many steps (``reg3d_interval`` 5 in the config)."""
    reg3d_k: int = 5
    """Neighbours per sampled Gaussian, itself included (``reg3d_k`` 5)."""
    reg3d_sample_size: int = 1000
    """Gaussians sampled per regulariser step (``reg3d_sample_size`` 1000)."""
    reg3d_max_points: int = 200000
    """The neighbours are searched among at most this many Gaussians, a random subset (``reg3d_max_points`` 200k)."""
    lr: GroupingRates = field(default_factory=GroupingRates)
    """Learning rates (``model.lr.<group>``)."""
    loss_weights: GroupingWeights = field(default_factory=GroupingWeights)
    """The family's loss terms' weights (``model.loss_weights.<term>``)."""
