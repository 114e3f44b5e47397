"""The weighted loss sets of GP-NeRF's Table 4 (``rgb``, ``ce``, ``sd``, ``dgs``), built by one class, and
``label_free`` (``rgb`` + ``sd`` + ``dgs``, for scenes without labels), a subclass that refuses a cross-entropy.

Default weights, in this module's normalisations, and what GP-NeRF's code effectively uses (ScanNet):

========  =======  ==========================================================================
term      default  reference code, expressed in our normalisation
========  =======  ==========================================================================
rgb       1.0      0.25 x channel-summed squared error = 0.75 x our per-channel MSE (per pass)
ce        1.0      0.75, counted twice = 1.5 (the double count is a bug, C13)
sd        0.25     0.25 (Replica: 0.5)
dgs       0.25     0.25 of a mean over all R x 64 samples = 0.25 x 5/64 of our window mean
========  =======  ==========================================================================

rgb and ce keep GNT's and the usual unit weights; sd and dgs keep the code's distillation scale, with
the D.G term averaged over the window samples it actually supervises. A parity experiment sets the
right-hand column explicitly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

from torch import Tensor

from gpnerf_core import ConfigError, ImageLossInputs, LossInputs, LossSet, Predicts, gather_cells, pixel_cells
from gpnerf_plugins.losses.terms import (
    centre_from_depth,
    centre_from_weights,
    cosine_distance,
    cross_entropy,
    depth_guided_distance,
    rgb_l1,
    rgb_mse,
    sample_window,
    structural_dissimilarity,
)

DGS_CENTERS = ("pred_weights", "gt_depth")


@dataclass
class LossSetConfig:
    """Options shared by every loss set; the defaults are the full GP-NeRF set (``dgs``)."""

    name: str = "dgs"
    """Registry name of the loss set."""
    rgb_weight: float = 1.0
    """Weight of the colour MSE (coarse + fine pass)."""
    ce_weight: float = 1.0
    """Weight of the semantic cross-entropy of the head's logits (counted once)."""
    sd_weight: float = 0.25
    """Weight of the 2D semantic distillation (rendered feature vs teacher)."""
    dgs_weight: float = 0.25
    """Weight of the depth-guided semantic distillation (per-sample features vs teacher)."""
    teacher_stop_grad: bool = True
    """Gradient block: detach the teacher in the S.D and D.G terms."""
    dgs_window: int = 2
    """N_p: the D.G window spans 2 * N_p + 1 sample indices around its centre."""
    dgs_center: str = "pred_weights"
    """D.G window centre: 'pred_weights' (argmax of the weights) or 'gt_depth' (sample nearest the GT depth)."""
    dgs_push_away: bool = False
    """D.G also adds max(0, cos) averaged over the samples outside the window (the paper's push-away)."""


@dataclass
class RgbLossConfig(LossSetConfig):
    """GNT only: colour."""

    name: str = "rgb"
    """Registry name of the loss set."""
    ce_weight: float = 0.0
    """Weight of the semantic cross-entropy (off)."""
    sd_weight: float = 0.0
    """Weight of the 2D semantic distillation (off)."""
    dgs_weight: float = 0.0
    """Weight of the depth-guided semantic distillation (off)."""


@dataclass
class CeLossConfig(LossSetConfig):
    """Colour and semantic cross-entropy (Table 4, IDs 1-2)."""

    name: str = "ce"
    """Registry name of the loss set."""
    sd_weight: float = 0.0
    """Weight of the 2D semantic distillation (off)."""
    dgs_weight: float = 0.0
    """Weight of the depth-guided semantic distillation (off)."""


@dataclass
class SdLossConfig(LossSetConfig):
    """Colour, cross-entropy and 2D semantic distillation (Table 4, IDs 3-4 by ``teacher_stop_grad``)."""

    name: str = "sd"
    """Registry name of the loss set."""
    dgs_weight: float = 0.0
    """Weight of the depth-guided semantic distillation (off)."""


@dataclass
class DgsLossConfig(LossSetConfig):
    """All four terms (Table 4, ID 5)."""

    name: str = "dgs"
    """Registry name of the loss set."""


@dataclass
class LabelFreeLossConfig(LossSetConfig):
    """Colour and both distillations from the 2D teacher, no label anywhere: adapting a trained model to scenes
    without labels (a user's own capture). The teacher is the extractor's own features of the target image."""

    name: str = "label_free"
    """Registry name of the loss set."""
    ce_weight: float = 0.0
    """The cross-entropy reads labels; this loss set has none (must stay 0)."""


@dataclass
class ImageLossConfig(LossSetConfig):
    """Colour on whole images, MSE and D-SSIM, and the cross-entropy, for a family that renders whole images
    (``TrainingBatch.IMAGES``: Gaussian splatting). MVSplat's loss is MSE + 0.05 LPIPS; LPIPS needs pretrained weights
    that cannot be downloaded here, so the structural term is SSIM's, 3D Gaussian splatting's D-SSIM."""

    name: str = "image"
    """Registry name of the loss set."""
    rgb_error: str = "mse"
    """The colour term's error per pixel and channel: ``mse`` (MVSplat's) or ``l1`` (3D Gaussian splatting's, weighted
    0.8 beside its 0.2 D-SSIM)."""
    ssim_weight: float = 0.05
    """Weight of ``1 - SSIM`` of the rendered image against the target (MVSplat's LPIPS weight; 3DGS: 0.2 with its L1
    at 0.8)."""
    sd_weight: float = 0.0
    """Weight of the 2D semantic distillation (off; on for a family with a head: 0.25)."""
    dgs_weight: float = 0.0
    """Weight of the depth-guided distillation (off: a rasterizing family has no samples along its rays)."""


class WeightedLossSet(LossSet):
    """Returns the weighted terms ``rgb``, ``ce``, ``sd``, ``dgs`` whose weight is non-zero.

    Args: the fields of ``LossSetConfig`` except ``name``, and ``extra_weights``: weights of the terms a subclass
    adds, by term name, each computed by the subclass's method ``_<term>(inputs)``.
    """

    def __init__(
        self,
        rgb_weight: float = LossSetConfig.rgb_weight,
        ce_weight: float = LossSetConfig.ce_weight,
        sd_weight: float = LossSetConfig.sd_weight,
        dgs_weight: float = LossSetConfig.dgs_weight,
        teacher_stop_grad: bool = LossSetConfig.teacher_stop_grad,
        dgs_window: int = LossSetConfig.dgs_window,
        dgs_center: str = LossSetConfig.dgs_center,
        dgs_push_away: bool = LossSetConfig.dgs_push_away,
        extra_weights: Mapping[str, float] | None = None,
    ) -> None:
        super().__init__()
        weights = {"rgb": rgb_weight, "ce": ce_weight, "sd": sd_weight, "dgs": dgs_weight, **(extra_weights or {})}
        for term, weight in weights.items():
            if not math.isfinite(weight) or weight < 0:
                raise ConfigError(f"loss.{term}_weight={weight}: expected a finite weight >= 0")
        if not any(weights.values()):
            names = ", ".join(f"{term}_weight" for term in weights)
            raise ConfigError(f"every loss weight ({names}) is 0; nothing to train")
        if dgs_center not in DGS_CENTERS:
            raise ConfigError(f"loss.dgs_center={dgs_center!r}: expected one of {', '.join(DGS_CENTERS)}")
        if dgs_window < 0:
            raise ConfigError(f"loss.dgs_window={dgs_window}: expected 0 or more sample indices")
        self.weights = {term: float(w) for term, w in weights.items() if w > 0}
        self.teacher_stop_grad = bool(teacher_stop_grad)
        self.dgs_window = int(dgs_window)
        self.dgs_center = dgs_center
        self.dgs_push_away = bool(dgs_push_away)
        self.needs_semantics = any(term != "rgb" for term in self.weights)
        self.needs_sample_semantics = "dgs" in self.weights
        self.head_predicts = Predicts.CLASSES if "ce" in self.weights else None
        # rgb, sd and dgs read colours, the teacher and (gt_depth centre) depth; only the cross-entropy reads labels.
        self.needs_labels = "ce" in self.weights

    def forward(self, inputs: LossInputs | ImageLossInputs) -> dict[str, Tensor]:
        """Weighted scalar terms by name for one target view, of rays (``LossInputs``) or whole images
        (``ImageLossInputs``); the total is their sum."""
        return {term: weight * getattr(self, f"_{term}")(inputs) for term, weight in self.weights.items()}

    def _teacher(self, teacher: Tensor | None, term: str) -> Tensor:
        if teacher is None:
            raise ConfigError(f"loss term {term!r} needs the teacher features of the target view; the model gave none")
        return teacher.detach() if self.teacher_stop_grad else teacher

    @staticmethod
    def _rgb(inputs: LossInputs | ImageLossInputs) -> Tensor:
        """Per pass; on whole images of a masked frame, at the pixels its mask keeps."""
        if isinstance(inputs, ImageLossInputs):
            return rgb_mse(*kept_pixels(inputs.output.rgb, inputs.target_rgb, inputs.valid))
        loss = rgb_mse(inputs.coarse.rgb, inputs.target_rgb)
        if inputs.fine is not None:
            loss = loss + rgb_mse(inputs.fine.rgb, inputs.target_rgb)
        return loss

    @staticmethod
    def _ce(inputs: LossInputs | ImageLossInputs) -> Tensor:
        """On the head's map; for a label-rendering model on its per-pixel scores (whole images) or on each pass's
        per-ray scores (coarse + fine, as Semantic-NeRF)."""
        if isinstance(inputs, ImageLossInputs):
            output = inputs.output
            scores = output.logits if output.logits is not None else output.scores
            if scores is not None and inputs.labels is not None:
                return cross_entropy(scores, inputs.labels[None], inputs.ignore_index)
        elif inputs.logits is not None and inputs.labels is not None:
            return cross_entropy(inputs.logits, inputs.labels, inputs.ignore_index)
        else:
            passes = [p for p in (inputs.coarse, inputs.fine) if p is not None and p.logits is not None]
            if passes and inputs.labels_at_rays is not None:
                labels = inputs.labels_at_rays[None, :, None]  # [1, R, 1]: the rays as a one-pixel-wide image
                return sum(cross_entropy(p.logits.T[None, :, :, None], labels, inputs.ignore_index) for p in passes)
        raise ConfigError("loss term 'ce' needs semantic scores and labels; select a head (+head=<name>) or a model "
                          "that renders labels")

    def _sd(self, inputs: LossInputs | ImageLossInputs) -> Tensor:
        """Rendered features against the teacher's: at the rays, or at every pixel of whole images (each map read at
        the pixel's cell)."""
        if isinstance(inputs, ImageLossInputs):
            output = inputs.output
            if output.semantic is None:
                raise ConfigError("loss term 'sd' needs a rendered semantic map; the model gave none")
            teacher = self._teacher(output.teacher_map, "sd")
            size = tuple(inputs.target_rgb.shape[:2])
            device = output.semantic.device
            student = gather_cells(output.semantic, pixel_cells(size, tuple(output.semantic.shape[-2:]), device))
            return cosine_distance(student, gather_cells(teacher, pixel_cells(size, tuple(teacher.shape[-2:]), device)))
        if inputs.last.semantic is None:
            raise ConfigError("loss term 'sd' needs rendered semantic features; the semantic field is off")
        return cosine_distance(inputs.last.semantic, self._teacher(inputs.teacher_at_rays, "sd"))

    def _dgs(self, inputs: LossInputs | ImageLossInputs) -> Tensor:
        if isinstance(inputs, ImageLossInputs):
            raise ConfigError("loss term 'dgs' distils per-sample features along rays, and the model renders whole "
                              "images without samples; set loss.dgs_weight=0")
        last = inputs.last
        if last.sample_semantic is None:
            raise ConfigError("loss term 'dgs' needs per-sample semantic features; the semantic field is off")
        if self.dgs_center == "gt_depth":
            centre = centre_from_depth(last.samples.depths, inputs.target_depth, last.weights)
        else:
            centre = centre_from_weights(last.weights)
        window = sample_window(centre, last.sample_semantic.shape[1], self.dgs_window)
        return depth_guided_distance(last.sample_semantic, self._teacher(inputs.teacher_at_rays, "dgs"), window,
                                     self.dgs_push_away)


def kept_pixels(rendered: Tensor, target: Tensor, valid: Tensor | None) -> tuple[Tensor, Tensor]:
    """``[H, W, C]`` images as they are, or ``[N, C]`` at the ``valid`` ``[H, W]`` pixels of a masked frame."""
    return (rendered, target) if valid is None else (rendered[valid], target[valid])


class LabelFreeLossSet(WeightedLossSet):
    """``rgb``, ``sd`` and ``dgs`` of ``WeightedLossSet``, refusing a cross-entropy weight: it trains without labels.

    Every term reads only what an unlabelled scene has: the target colours, the teacher features of the target image
    (``sd``, and ``dgs`` around the predicted weights' peak, or around the GT depth where ``dgs_center=gt_depth`` and
    the frame has depth). Args: the fields of ``LabelFreeLossConfig`` except ``name``.
    """

    def __init__(self, **options: float | bool | str) -> None:
        ce_weight = float(options.pop("ce_weight", 0.0))
        if ce_weight != 0.0:
            raise ConfigError(
                f"loss.ce_weight={ce_weight}: the label_free loss set trains without labels; expected 0 "
                "(a loss set with the cross-entropy: +loss=dgs)"
            )
        super().__init__(ce_weight=0.0, **options)


RGB_ERRORS = ("mse", "l1")
"""The colour errors of the ``image`` loss set (``ImageLossConfig.rgb_error``)."""


class ImageLossSet(WeightedLossSet):
    """``WeightedLossSet``'s terms and ``ssim``: ``1 - SSIM`` of the rendered image against the target, which needs a
    family that renders whole images (``ImageLossInputs``; rays are refused in one line). Args: the fields of
    ``ImageLossConfig`` except ``name``."""

    def __init__(self, *, ssim_weight: float = ImageLossConfig.ssim_weight, rgb_error: str = ImageLossConfig.rgb_error,
                 **options: float | bool | str) -> None:
        if rgb_error not in RGB_ERRORS:
            raise ConfigError(f"loss.rgb_error={rgb_error!r}: expected one of {', '.join(RGB_ERRORS)}")
        super().__init__(**options, extra_weights={"ssim": float(ssim_weight)})
        self.rgb_error = rgb_error
        self.needs_semantics = any(term not in ("rgb", "ssim") for term in self.weights)
        self.needs_whole_images = "ssim" in self.weights

    def _rgb(self, inputs: LossInputs | ImageLossInputs) -> Tensor:
        """``WeightedLossSet``'s MSE, or the mean absolute error per pass (``rgb_error=l1``)."""
        if self.rgb_error == "mse":
            return WeightedLossSet._rgb(inputs)
        if isinstance(inputs, ImageLossInputs):
            return rgb_l1(*kept_pixels(inputs.output.rgb, inputs.target_rgb, inputs.valid))
        return sum(rgb_l1(p.rgb, inputs.target_rgb) for p in (inputs.coarse, inputs.fine) if p is not None)

    @staticmethod
    def _ssim(inputs: LossInputs | ImageLossInputs) -> Tensor:
        """On the rendered image, at the pixels a masked frame's mask keeps."""
        if not isinstance(inputs, ImageLossInputs):
            raise ConfigError("loss term 'ssim' compares whole images, and the model renders random rays; use a model "
                              "that renders whole images (Capabilities.trains_on = TrainingBatch.IMAGES)")
        return structural_dissimilarity(inputs.output.rgb.permute(2, 0, 1).contiguous(),
                                        inputs.target_rgb.permute(2, 0, 1).contiguous(), inputs.valid)
