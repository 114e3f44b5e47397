"""Interface of loss sets: named, weighted groups of loss terms."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.types import ImageLossInputs, LossInputs


class LossSet(nn.Module, ABC):
    """Computes the weighted terms of one training step.

    The flags tell the pipeline what to compute, so a loss set that ignores semantics costs nothing there.
    """

    needs_semantics: bool = False
    """Render semantic features and run the head on the fused map."""
    needs_sample_semantics: bool = False
    """Also return per-sample semantic features (``RenderedRays.sample_semantic``)."""
    needs_instances: bool = False
    """Target views carry the frames' instance ids (``LossInputs.instances``); a dataset without them is refused
    before training."""
    needs_labels: bool = True
    """Some term reads the target's labels (class ids or instance ids). Training on a scene without labels
    (``Scene.labelled`` False, its labels all ``ignore_index``) is then refused before any work. True unless the loss
    set says otherwise, so a loss set that never declared it is never trained silently on empty labels; a loss set
    whose terms need none (colour, distillation from the 2D teacher) sets it False."""
    needs_whole_images: bool = False
    """Some term reads whole images (``ImageLossInputs``, e.g. SSIM): only a family that trains on whole images
    (``Capabilities.trains_on``) can use it; another is refused when the run is built."""
    head_predicts: Predicts | None = None
    """What the model's semantic scores must be for this loss set (``Predicts``), or None (none needed, or either)."""

    @abstractmethod
    def forward(self, inputs: LossInputs | ImageLossInputs) -> dict[str, Tensor]:
        """Return scalar terms by name for one target view, each already multiplied by its weight; the total is their
        sum. ``inputs`` is a ray family's ``LossInputs`` or, from a family that trains on whole images,
        ``ImageLossInputs``; a term that cannot read the one it is given raises a ConfigError saying why."""
