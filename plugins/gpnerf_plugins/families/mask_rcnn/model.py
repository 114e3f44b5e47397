"""Mask R-CNN as a per-scene model family: a 2D instance segmenter fitted on one scene's training frames and their
instance masks, scoring the **real** RGB of the held-out frames (``Capabilities.segments_image``: evaluation hands it
``TargetCamera.image``; it renders no colour, depth or novel pose). Its five losses are the family's own terms
(``Capabilities.loss_terms``, weighted by ``model.loss_weights``), computed in the training forward, where the
anchors and proposals are sampled against each frame's boxes (as detectron2's and torchvision's models return
their losses); no loss set is configured."""

from __future__ import annotations

import logging
from typing import Any, Mapping

import torch
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    ConfigError,
    DataError,
    FamilyHooks,
    ImageOutput,
    ImportedWeights,
    ModelFamily,
    Prediction,
    Predicts,
    SemanticMode,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    TrainingBatch,
    TrainingState,
)
from gpnerf_plugins.families.mask_rcnn.detector import LOSS_NAMES, DetectorSettings, MaskRCNN
from gpnerf_plugins.families.mask_rcnn.roi_heads import Detections
from gpnerf_plugins.families.mask_rcnn.targets import InstanceTargets, paste_masks, slot_logits, targets_from_ids
from gpnerf_plugins.families.mask_rcnn.torchvision_keys import FORMAT, is_torchvision, map_torchvision

log = logging.getLogger(__name__)


class MaskRCNNHooks(FamilyHooks):
    """The detector's five loss terms, as its training forward left them in each view's ``ImageOutput.extras``
    (averaged over the step's views)."""

    def loss_terms(self, state: TrainingState, wanted: frozenset[str]) -> Mapping[str, Tensor]:
        views = state.outputs.views
        return {name: sum(view.extras["losses"][name] for view in views) / len(views) for name in wanted}


class MaskRCNNFamily(ModelFamily):
    """Mask R-CNN on whole frames (module docstring).

    Args:
        settings: the detector's (``DetectorSettings``); its ``roi.detections_per_image`` are the instance slots of
            ``Prediction.logits``.
    """

    capabilities = Capabilities(generalizable=False, accepts_head=False, trains_on=TrainingBatch.IMAGES,
                                source_encoding=None, segments_image=True, loss_terms=LOSS_NAMES, hooks=MaskRCNNHooks,
                                foreign_weights=True)

    def __init__(self, *, settings: DetectorSettings) -> None:
        super().__init__()
        self.detector = MaskRCNN(settings)
        self.slots = settings.roi.detections_per_image
        self.anchor_sizes = settings.anchor_sizes
        self._warned_slots = False

    @property
    def semantic_output(self) -> SemanticOutput:
        return SemanticOutput(Predicts.INSTANCES, SemanticMode.LABEL_RENDERING, self.slots + 1, self.slots,
                              slot_activation="sigmoid")

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"detector": list(self.detector.parameters())}

    def check_image_size(self, height: int, width: int) -> None:
        """Anchors larger than the image's longer side (as resized: ``model.min_size``) are refused: no box of the
        image can match them."""
        largest, settings = max(self.anchor_sizes), self.detector.settings
        side = max(height, width)
        if settings.min_size:
            side = side * min(settings.min_size / min(height, width), settings.max_size / side)
        if largest > side:
            raise ConfigError(f"model.anchor_sizes={list(self.anchor_sizes)}: an anchor of {largest:g} px is larger "
                              f"than the {height} x {width} images; expected sizes up to {int(side)} px")

    def read_foreign(self, checkpoint: Mapping[str, Any]) -> ImportedWeights | None:
        """torchvision's ``maskrcnn_resnet50_fpn`` state dict (its COCO checkpoint, read from a local file), for
        ``model.backbone=resnet50`` with its widths and ``model.classes=90`` (``torchvision_keys``)."""
        if not is_torchvision(checkpoint):
            return None
        tensors = map_torchvision(list(self.state_dict()), checkpoint)
        return ImportedWeights(tensors=tensors, format=FORMAT, offered=tuple(checkpoint))

    # ---- training ---------------------------------------------------------------------------------------------------

    def _targets(self, view: TargetView) -> InstanceTargets:
        """The view's ground truth from its instance ids (every id one object); more ids than ``model.slots`` is said
        once."""
        if view.instances is None:
            raise DataError(f"scene {view.scene!r} frame {view.frame}: no instance ids to train model=mask_rcnn on; "
                            "use a dataset with instance ids")
        targets = targets_from_ids(view.instances)
        if len(targets.boxes) > self.slots and not self._warned_slots:
            self._warned_slots = True
            log.warning("scene %r frame %d has %d instance ids (background included), more than model.slots=%d "
                        "detections per image: at most %d can be found; set model.slots >= %d (said once)",
                        view.scene, view.frame, len(targets.boxes), self.slots, self.slots, len(targets.boxes))
        return targets

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        """Each view's five loss terms (``ImageOutput.extras["losses"]``); with ``semantics`` also its detections as
        slot scores (``ImageOutput.scores``, differentiable through the box and mask heads). Colour and depth are
        zeros: a 2D model renders neither."""
        outputs = []
        for view in batch.views:
            image = view.image[None]
            generator = torch.Generator().manual_seed(int(view.render_seed))
            losses = self.detector.losses(image, [self._targets(view)], generator)
            scores = self._slot_scores(self.detector.detect(image)[0], image) if semantics else None
            height, width = view.camera.image_size
            outputs.append(ImageOutput(rgb=image.new_zeros(height, width, 3), depth=image.new_zeros(height, width),
                                       scores=scores, extras={"losses": losses}))
        return StepOutput(tuple(outputs))

    def _slot_scores(self, detections: Detections, image: Tensor) -> Tensor:
        """``[1, slots + 1, H, W]`` logits of the detections pasted into the image (``targets.slot_logits``)."""
        masks = paste_masks(detections.masks, detections.boxes, image.shape[-2], image.shape[-1])
        return slot_logits(masks, detections.scores, self.slots)

    # ---- whole views ------------------------------------------------------------------------------------------------

    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: object = None) -> Prediction:
        """The detections on the camera's real image (``TargetCamera.image``, which only evaluation gives) as slot
        scores at full size; colour and depth zeros on the ``stride`` grid (a 2D model renders neither)."""
        if camera.image is None:
            raise ConfigError("model=mask_rcnn segments a real image (a 2D baseline) and renders no novel view: it "
                              "scores held-out frames in eval only (not render, view, export or a trajectory)")
        image = camera.image.permute(2, 0, 1)[None].float()
        with torch.inference_mode():
            logits = self._slot_scores(self.detector.detect(image)[0], image)
        s = max(1, int(stride))
        h, w = camera.height // s, camera.width // s
        return Prediction(rgb=image.new_zeros(h, w, 3), depth=image.new_zeros(h, w), semantic=None, logits=logits,
                          stride=s)
