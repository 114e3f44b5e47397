"""Evaluation metrics, each stored under a protocol id; numbers with different ids are never compared.

Segmentation follows Semantic-NeRF / GP-NeRF per image (REFERENCE.md §6) and also reports dataset-level
numbers from one confusion matrix (REFERENCE.md C11). Image quality clamps RGB to [0, 1] first (C12) and
uses scikit-image. Every public function returns plain Python numbers (or None), ready for JSON.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.runtime.finite import all_finite

MIOU_IMAGE_MEAN_PRESENT = "miou/image_mean_present"
"""The paper's mIoU. Per image: drop GT-ignore pixels, IoU_k = TP/(TP+FP+FN) for every class k present in that
image's GT, mIoU = their mean (a class only predicted still costs its true class through FP/FN). Images without
any valid GT pixel are excluded and counted. The per-image values are averaged within each group (scene), then
the group means are averaged."""

MIOU_DATASET = "miou/dataset"
"""One confusion matrix summed over every evaluated pixel (GT-ignore dropped); IoU_k = TP/(TP+FP+FN) for every class
that appears in the GT or in the prediction; mIoU = their mean. Classes absent from both are excluded (never 1.0)."""

ACC_TOTAL = "acc/total"
"""Dataset-level pixel accuracy: trace / sum of the summed confusion matrix (GT-ignore pixels dropped)."""

ACC_CLASS_MEAN = "acc/class_mean"
"""Dataset-level mean class accuracy: mean over classes present in the GT of TP_k / GT_k from the summed confusion
matrix (a class never in the GT has no recall and is excluded)."""

ACC_IMAGE_TOTAL = "acc/image_total"
"""Paper-style total accuracy: per image trace / sum (GT-ignore dropped), averaged within groups, then over groups."""

ACC_IMAGE_CLASS_MEAN_PRESENT = "acc/image_class_mean_present"
"""Paper-style average accuracy: per image the mean of TP_k / GT_k over classes present in that image's GT,
averaged within groups, then over groups."""

IOU_DATASET_PER_CLASS = "iou/dataset_per_class"
"""List of K per-class IoUs from the summed confusion matrix; None for a class absent from both GT and prediction."""

PSNR_CLAMPED = "psnr/clamped"
"""Per image -10 log10(MSE) in dB with prediction and GT clamped to [0, 1] (data range 1), MSE over all pixels and
channels (skimage ``peak_signal_noise_ratio``); averaged within groups, then over groups. Identical images give
+inf; a mean that is +inf is reported as None (JSON has no infinity)."""

SSIM_GAUSSIAN11 = "ssim/gaussian11"
"""Per image Wang et al. SSIM on [0, 1]-clamped RGB: 11x11 Gaussian window (sigma 1.5), population covariance,
C1 = 0.01^2, C2 = 0.03^2, per channel, averaged over the map without the 5-pixel border (skimage
``structural_similarity``; the official code zero-pads and keeps the border, which differs slightly at the
edges); averaged within groups, then over groups."""

LPIPS_VGG = "lpips/vgg"
"""LPIPS with the VGG backbone on [0, 1] inputs rescaled to [-1, 1]. Not computed by gpnerf-core (see
:func:`lpips_vgg_status`); always None with a reason under :data:`LPIPS_VGG_REASON`."""

LPIPS_VGG_REASON = "lpips/vgg_unavailable_reason"
"""Why :data:`LPIPS_VGG` is None."""

DEPTH_ABS_REL = "depth/abs_rel"
"""Per image mean of ``|d - d*| / d*`` over the rendered cells (``eval.render_stride`` pixels a side) whose every pixel
has ground-truth depth (camera z in metres, 0 = unknown), ``d*`` the mean of the cell's pixels and ``d`` the rendered
depth; averaged within groups, then over groups. Images without such a cell are left out (counted in
:data:`COUNT_IMAGES_WITH_DEPTH`); None when no image has one, with the reason under :data:`DEPTH_UNAVAILABLE_REASON`."""

DEPTH_RMSE = "depth/rmse"
"""Per image ``sqrt(mean (d - d*)^2)`` in metres over the same cells as :data:`DEPTH_ABS_REL`; averaged within groups,
then over groups."""

DEPTH_UNAVAILABLE_REASON = "depth/unavailable_reason"
"""Why :data:`DEPTH_ABS_REL` and :data:`DEPTH_RMSE` are None (no evaluated frame has ground-truth depth)."""

COUNT_IMAGES_WITH_DEPTH = "count/images_with_depth"
"""Number of images that entered the depth protocols."""

FEATURE_COSINE = "features/cosine_image_mean"
"""Feature fidelity of a feature field (``+feature_provider``). Per image: the rendered field (``Prediction.features``,
in the provider's channels, decoded where compressed) brought to the provider's grid (the mean over each cell's
pixels, ``gpnerf_core.features.field.to_grid``), the cosine similarity with the provider's features of the real
held-out frame cell by cell, averaged over the cells; averaged within groups (scenes), then over groups. Absent
without a feature field."""

COUNT_IMAGES_WITH_FEATURES = "count/images_with_features"
"""Number of images that entered :data:`FEATURE_COSINE`."""

LABELS_UNAVAILABLE_REASON = "labels/unavailable_reason"
"""Why every label metric of a split is None: none of its scenes has labels (``Scene.labelled`` False, a capture
without labels). The label metrics are :data:`SEGMENTATION_KEYS` and the ``baseline_majority`` and ``teacher_2d``
references for a class head, the instance APs (:data:`gpnerf_core.evaluation.instances.AP_KEYS`) and ``teacher_2d``
for an instance head; each is None, never 0. Present only in such a split."""

LABELS_UNLABELLED_SCENES = "labels/unlabelled_scenes"
"""The scenes of a split without labels when the split also has labelled ones: every label metric is computed on the
labelled scenes only (the image-quality and depth protocols on all). Present only in such a split."""

COUNT_IMAGES_WITHOUT_LABELS = "count/images_without_labels"
"""Images of the scenes in :data:`LABELS_UNLABELLED_SCENES` (in the image-quality and depth protocols only)."""

BASELINE_MAJORITY_UNAVAILABLE_REASON = "baseline_majority_unavailable_reason"
"""Why a split's ``baseline_majority`` is None although its labels are scored: no training scene has labels to take
the majority class from."""

QUERY_PROTOTYPE = "query/nearest_prototype"
"""The query protocol (``eval.query_protocol=true``; ``gpnerf_core/evaluation/query_protocol.py``): per labelled scene,
each class's prototype is the mean normalised feature of its pixels in ``prototype_frames`` of the scene's training
frames that show it (drawn by ``seed``), rendered at their own cameras; every scored held-out frame is labelled by
nearest prototype (cosine) and scored with the segmentation protocols (:data:`SEGMENTATION_KEYS`, per-image mIoU
first) per feature source (``feature_field``, ``semantic_embedding``, ``provider_2d``). Its numbers answer how well a
feature space segments from one example per class; they are never compared with a class head's mIoU as the same
protocol, only shown beside it."""

COUNT_IMAGES = "count/images"
"""Number of images that entered the per-image protocols."""

COUNT_IMAGES_WITHOUT_VALID_GT = "count/images_without_valid_gt"
"""Number of images skipped because every GT pixel was the ignore label."""

COUNT_GROUPS = "count/groups"
"""Number of groups (scenes) with at least one image in the per-image protocols."""

DEFAULT_GROUP = "all"
"""Group used when the caller does not name one."""


# ----------------------------------------------------------------------------------------------------------------
# Segmentation


SEGMENTATION_KEYS = (
    MIOU_IMAGE_MEAN_PRESENT,
    ACC_IMAGE_TOTAL,
    ACC_IMAGE_CLASS_MEAN_PRESENT,
    MIOU_DATASET,
    ACC_TOTAL,
    ACC_CLASS_MEAN,
    IOU_DATASET_PER_CLASS,
)
"""The segmentation protocols of a class head (None, with :data:`LABELS_UNAVAILABLE_REASON`, on scenes without
labels)."""


def no_labels_reason(scenes: Sequence[str], shown: int = 5) -> str:
    """``scene 'a' has no labels`` / ``scenes 'a', 'b' have no labels`` (the first ``shown`` named)."""
    names = ", ".join(repr(name) for name in scenes[:shown])
    if len(scenes) > shown:
        names += f" and {len(scenes) - shown} more"
    return f"scene {names} has no labels" if len(scenes) == 1 else f"scenes {names} have no labels"


def _as_labels(labels: Tensor | np.ndarray, name: str) -> Tensor:
    tensor = torch.as_tensor(labels)
    if tensor.dtype.is_floating_point or tensor.dtype.is_complex or tensor.dtype == torch.bool:
        raise ValueError(f"{name} must hold integer class ids, got dtype {tensor.dtype}")
    return tensor.long()


def confusion_matrix(
    pred: Tensor | np.ndarray,
    target: Tensor | np.ndarray,
    num_classes: int,
    ignore_index: int | None = None,
) -> Tensor:
    """Count (ground truth, prediction) pairs.

    Args:
        pred: ``[...]`` integer predicted classes, every value in ``[0, num_classes)``.
        target: same shape, ground-truth classes in ``[0, num_classes)`` or ``ignore_index``.
        num_classes: K.
        ignore_index: GT label whose pixels are dropped (None: no label is ignored).

    Returns:
        ``[K, K]`` int64 on ``target``'s device; rows are GT classes, columns predicted classes.

    Raises:
        ValueError: a prediction outside ``[0, K)``, a GT label that is neither valid nor ignore, or a shape mismatch.
    """
    if num_classes < 1:
        raise ValueError(f"num_classes must be >= 1, got {num_classes}")
    target = _as_labels(target, "target")
    pred = _as_labels(pred, "pred").to(target.device)
    if pred.shape != target.shape:
        raise ValueError(f"pred shape {list(pred.shape)} does not match target shape {list(target.shape)}")
    pred = pred.reshape(-1)
    target = target.reshape(-1)
    bad_pred = (pred < 0) | (pred >= num_classes)
    if bool(bad_pred.any()):
        value = int(pred[bad_pred][0])
        raise ValueError(
            f"predicted class {value} is outside [0, {num_classes}); heads must predict valid classes only "
            "(mask an 'ignore' logit before argmax)"
        )
    if ignore_index is not None:
        keep = target != ignore_index
        pred = pred[keep]
        target = target[keep]
    bad_target = (target < 0) | (target >= num_classes)
    if bool(bad_target.any()):
        value = int(target[bad_target][0])
        raise ValueError(
            f"ground-truth label {value} is neither in [0, {num_classes}) nor the ignore index {ignore_index}"
        )
    counts = torch.bincount(target * num_classes + pred, minlength=num_classes * num_classes)
    return counts.reshape(num_classes, num_classes)


def _confusion_parts(confusion: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True positives, GT counts (row sums) and prediction counts (column sums), float64."""
    matrix = confusion.detach().cpu().to(torch.float64).numpy()
    return np.diag(matrix).copy(), matrix.sum(axis=1), matrix.sum(axis=0)


def image_scores_from_confusion(confusion: Tensor) -> dict[str, float] | None:
    """The paper's per-image scores from one image's confusion matrix.

    Args:
        confusion: ``[K, K]`` counts of one image (rows GT, columns prediction).

    Returns:
        ``{MIOU_IMAGE_MEAN_PRESENT, ACC_IMAGE_TOTAL, ACC_IMAGE_CLASS_MEAN_PRESENT}`` as floats in [0, 1], or None
        when the image has no valid GT pixel (the caller excludes and counts it).
    """
    tp, gt_count, pred_count = _confusion_parts(confusion)
    total = gt_count.sum()
    if total == 0:
        return None
    present = gt_count > 0
    union = gt_count + pred_count - tp
    iou = tp[present] / union[present]
    recall = tp[present] / gt_count[present]
    return {
        MIOU_IMAGE_MEAN_PRESENT: float(iou.mean()),
        ACC_IMAGE_TOTAL: float(tp.sum() / total),
        ACC_IMAGE_CLASS_MEAN_PRESENT: float(recall.mean()),
    }


def dataset_scores_from_confusion(confusion: Tensor) -> dict[str, Any]:
    """Dataset-level scores from a confusion matrix summed over many images.

    Args:
        confusion: ``[K, K]`` summed counts (rows GT, columns prediction).

    Returns:
        ``{MIOU_DATASET, ACC_TOTAL, ACC_CLASS_MEAN, IOU_DATASET_PER_CLASS}``; the three scalars are None when the
        matrix is empty, and per-class entries are None for classes absent from both GT and prediction.
    """
    tp, gt_count, pred_count = _confusion_parts(confusion)
    union = gt_count + pred_count - tp
    seen = union > 0
    per_class = [float(tp[k] / union[k]) if seen[k] else None for k in range(len(tp))]
    total = gt_count.sum()
    if total == 0:
        return {MIOU_DATASET: None, ACC_TOTAL: None, ACC_CLASS_MEAN: None, IOU_DATASET_PER_CLASS: per_class}
    present = gt_count > 0
    return {
        MIOU_DATASET: float((tp[seen] / union[seen]).mean()),
        ACC_TOTAL: float(tp.sum() / total),
        ACC_CLASS_MEAN: float((tp[present] / gt_count[present]).mean()),
        IOU_DATASET_PER_CLASS: per_class,
    }


def image_segmentation_metrics(
    pred: Tensor | np.ndarray,
    target: Tensor | np.ndarray,
    num_classes: int,
    ignore_index: int | None = None,
) -> dict[str, float] | None:
    """Per-image paper protocol for one ``[H, W]`` prediction; None when the image has no valid GT pixel."""
    return image_scores_from_confusion(confusion_matrix(pred, target, num_classes, ignore_index))


def _mean(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and np.isfinite(value) else None


def _group_then_mean(per_group: dict[str, list[float]]) -> float | None:
    """Mean within each group, then the mean of the group means (groups with no value are skipped)."""
    return _mean([float(np.mean(values)) for values in per_group.values() if values])


class SegmentationAccumulator:
    """Collects per-image and dataset-level segmentation metrics over an evaluation set.

    Args:
        num_classes: K; predictions must lie in ``[0, K)``.
        ignore_index: GT label to drop (None: none).

    A majority-class baseline is this accumulator fed with a constant prediction; see
    :func:`constant_prediction_metrics`.
    """

    _IMAGE_KEYS = (MIOU_IMAGE_MEAN_PRESENT, ACC_IMAGE_TOTAL, ACC_IMAGE_CLASS_MEAN_PRESENT)

    def __init__(self, num_classes: int, ignore_index: int | None = None) -> None:
        if num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {num_classes}")
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self._confusion: dict[str, Tensor] = {}
        self._image_scores: dict[str, dict[str, list[float]]] = {}
        self._without_valid_gt: dict[str, int] = {}

    def update(
        self, pred: Tensor | np.ndarray, target: Tensor | np.ndarray, group: str = DEFAULT_GROUP
    ) -> dict[str, float] | None:
        """Add one image.

        Args:
            pred: ``[H, W]`` predicted classes in ``[0, K)``.
            target: ``[H, W]`` GT classes or ``ignore_index``.
            group: the group (scene) the image belongs to.

        Returns:
            This image's per-image scores, or None if it had no valid GT pixel (then it is only counted).
        """
        return self.add_confusion(confusion_matrix(pred, target, self.num_classes, self.ignore_index), group)

    def add_confusion(self, confusion: Tensor, group: str = DEFAULT_GROUP) -> dict[str, float] | None:
        """Add one image given its ``[K, K]`` confusion matrix (rows GT, columns prediction); as ``update``.

        Feeding the matrices of a sharded evaluation in image order gives exactly the single-process metrics.
        """
        confusion = confusion.cpu()
        if tuple(confusion.shape) != (self.num_classes, self.num_classes):
            raise ValueError(f"confusion matrix has shape {list(confusion.shape)}; expected [{self.num_classes}, {self.num_classes}]")
        if group not in self._confusion:
            self._confusion[group] = torch.zeros_like(confusion)
            self._image_scores[group] = {key: [] for key in self._IMAGE_KEYS}
            self._without_valid_gt[group] = 0
        self._confusion[group] += confusion
        scores = image_scores_from_confusion(confusion)
        if scores is None:
            self._without_valid_gt[group] += 1
        else:
            for key in self._IMAGE_KEYS:
                self._image_scores[group][key].append(scores[key])
        return scores

    @property
    def confusion(self) -> Tensor:
        """``[K, K]`` int64 confusion matrix summed over all groups."""
        total = torch.zeros(self.num_classes, self.num_classes, dtype=torch.int64)
        for matrix in self._confusion.values():
            total += matrix
        return total

    def compute(self) -> dict[str, Any]:
        """All segmentation metrics over everything seen so far.

        Returns:
            ``{protocol id: value}`` with the per-image protocols (group-then-mean; None with no valid image),
            the dataset-level ones (see :func:`dataset_scores_from_confusion`), :data:`COUNT_IMAGES`,
            :data:`COUNT_IMAGES_WITHOUT_VALID_GT` and :data:`COUNT_GROUPS`.
        """
        result: dict[str, Any] = {
            key: _group_then_mean({g: s[key] for g, s in self._image_scores.items()}) for key in self._IMAGE_KEYS
        }
        result.update(dataset_scores_from_confusion(self.confusion))
        counted = [g for g, s in self._image_scores.items() if s[MIOU_IMAGE_MEAN_PRESENT]]
        result[COUNT_IMAGES] = sum(len(s[MIOU_IMAGE_MEAN_PRESENT]) for s in self._image_scores.values())
        result[COUNT_IMAGES_WITHOUT_VALID_GT] = sum(self._without_valid_gt.values())
        result[COUNT_GROUPS] = len(counted)
        return result

    def compute_per_group(self) -> dict[str, dict[str, Any]]:
        """The same metrics for each group on its own: ``{group: {protocol id: value}}``."""
        out: dict[str, dict[str, Any]] = {}
        for group, scores in self._image_scores.items():
            entry: dict[str, Any] = {key: _mean(scores[key]) for key in self._IMAGE_KEYS}
            entry.update(dataset_scores_from_confusion(self._confusion[group]))
            entry[COUNT_IMAGES] = len(scores[MIOU_IMAGE_MEAN_PRESENT])
            entry[COUNT_IMAGES_WITHOUT_VALID_GT] = self._without_valid_gt[group]
            out[group] = entry
        return out


def class_pixel_counts(
    labels: Iterable[Tensor | np.ndarray], num_classes: int, ignore_index: int | None = None
) -> list[int]:
    """Number of pixels of each class over a set of label maps (e.g. the training targets), ignore dropped.

    The majority class for :func:`constant_prediction_metrics` is the index of the largest count.
    """
    counts = torch.zeros(num_classes, dtype=torch.int64)
    for label_map in labels:
        flat = _as_labels(label_map, "labels").reshape(-1).cpu()
        if ignore_index is not None:
            flat = flat[flat != ignore_index]
        bad = (flat < 0) | (flat >= num_classes)
        if bool(bad.any()):
            raise ValueError(
                f"label {int(flat[bad][0])} is neither in [0, {num_classes}) nor the ignore index {ignore_index}"
            )
        counts += torch.bincount(flat, minlength=num_classes)
    return [int(c) for c in counts]


def constant_prediction_metrics(
    targets: Iterable[tuple[Tensor | np.ndarray, str]],
    class_index: int,
    num_classes: int,
    ignore_index: int | None = None,
) -> dict[str, Any]:
    """Metrics of predicting ``class_index`` at every pixel (the majority-class baseline).

    Args:
        targets: ``(target [H, W], group)`` pairs, the same evaluation targets the model is scored on.
        class_index: the class predicted everywhere (pass the most frequent *training* class).
        num_classes, ignore_index: as for :class:`SegmentationAccumulator`.

    Returns:
        :meth:`SegmentationAccumulator.compute` of the constant prediction.
    """
    if not 0 <= class_index < num_classes:
        raise ValueError(f"constant class {class_index} is outside [0, {num_classes})")
    accumulator = SegmentationAccumulator(num_classes, ignore_index)
    for target, group in targets:
        target_tensor = _as_labels(target, "target")
        accumulator.update(torch.full_like(target_tensor, class_index), target_tensor, group)
    return accumulator.compute()


# ----------------------------------------------------------------------------------------------------------------
# Image quality


def _as_rgb(image: Tensor | np.ndarray, name: str) -> np.ndarray:
    """``[H, W, 3]`` float64 numpy copy of a tensor or array; rejects other shapes and non-finite values."""
    if isinstance(image, Tensor):
        array = image.detach().to("cpu", torch.float64).numpy()
    else:
        array = np.asarray(image, dtype=np.float64)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name} must be an [H, W, 3] RGB image, got shape {list(array.shape)}")
    if not np.isfinite(array).all():
        raise NonFiniteError(f"{name} contains NaN or Inf values")
    return array


def _pair(pred: Tensor | np.ndarray, gt: Tensor | np.ndarray, clamp: bool) -> tuple[np.ndarray, np.ndarray]:
    pred_array, gt_array = _as_rgb(pred, "pred"), _as_rgb(gt, "gt")
    if pred_array.shape != gt_array.shape:
        raise ValueError(f"pred shape {list(pred_array.shape)} does not match gt shape {list(gt_array.shape)}")
    if clamp:
        pred_array, gt_array = np.clip(pred_array, 0.0, 1.0), np.clip(gt_array, 0.0, 1.0)
    return pred_array, gt_array


def psnr(pred: Tensor | np.ndarray, gt: Tensor | np.ndarray, clamp: bool = True) -> float:
    """PSNR in dB with data range 1 (protocol :data:`PSNR_CLAMPED` when ``clamp``).

    Args:
        pred, gt: ``[H, W, 3]`` RGB, nominally in [0, 1].
        clamp: clamp both to [0, 1] first; ``False`` scores raw (possibly out-of-range) colours as the
            official code does, which is a different protocol.

    Returns:
        ``-10 log10(MSE)``; +inf for identical images.
    """
    pred_array, gt_array = _pair(pred, gt, clamp)
    if np.array_equal(pred_array, gt_array):
        return float("inf")
    # skimage's peak_signal_noise_ratio(gt, pred, data_range=1) on float64, operation for operation (the test holds
    # them equal); not called, because its module imports scipy.stats: 0.4 s at the start of every evaluating command.
    mse = np.mean((gt_array - pred_array) ** 2, dtype=np.float64)
    return float(10 * np.log10(1.0 / mse))


_SSIM_WINDOW = 11


def ssim(pred: Tensor | np.ndarray, gt: Tensor | np.ndarray) -> float:
    """SSIM of two ``[H, W, 3]`` RGB images clamped to [0, 1] (protocol :data:`SSIM_GAUSSIAN11`).

    Both sides must be at least 11 pixels (the Gaussian window).
    """
    pred_array, gt_array = _pair(pred, gt, clamp=True)
    if min(pred_array.shape[:2]) < _SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {_SSIM_WINDOW}x{_SSIM_WINDOW}, got {list(pred_array.shape)}")
    from skimage.metrics import structural_similarity

    value = structural_similarity(
        gt_array,
        pred_array,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    return float(value)


class FeatureAccumulator:
    """Collects per-image :data:`FEATURE_COSINE` values and averages them within groups, then over groups."""

    def __init__(self) -> None:
        self._scores: dict[str, list[float]] = {}

    def add(self, cosine: float, group: str = DEFAULT_GROUP) -> None:
        self._scores.setdefault(group, []).append(float(cosine))

    def compute(self) -> dict[str, Any]:
        """``{FEATURE_COSINE, COUNT_IMAGES_WITH_FEATURES}``; empty before any image."""
        if not self._scores:
            return {}
        return {FEATURE_COSINE: _finite_or_none(_group_then_mean(self._scores)),
                COUNT_IMAGES_WITH_FEATURES: sum(len(values) for values in self._scores.values())}


class ImageQualityAccumulator:
    """Collects per-image PSNR and SSIM and averages them within groups, then over groups."""

    _KEYS = (PSNR_CLAMPED, SSIM_GAUSSIAN11)

    def __init__(self) -> None:
        self._scores: dict[str, dict[str, list[float]]] = {}

    def update(
        self, pred: Tensor | np.ndarray, gt: Tensor | np.ndarray, group: str = DEFAULT_GROUP
    ) -> dict[str, float]:
        """Add one image pair (``[H, W, 3]`` each); returns its ``{PSNR_CLAMPED, SSIM_GAUSSIAN11}``."""
        scores = {PSNR_CLAMPED: psnr(pred, gt, clamp=True), SSIM_GAUSSIAN11: ssim(pred, gt)}
        self.add_scores(scores, group)
        return scores

    def add_scores(self, scores: dict[str, float], group: str = DEFAULT_GROUP) -> None:
        """Add one image's ``{PSNR_CLAMPED, SSIM_GAUSSIAN11}`` computed elsewhere (a sharded evaluation)."""
        bucket = self._scores.setdefault(group, {key: [] for key in self._KEYS})
        for key in self._KEYS:
            bucket[key].append(scores[key])

    def compute(self) -> dict[str, Any]:
        """``{PSNR_CLAMPED, SSIM_GAUSSIAN11, COUNT_IMAGES, COUNT_GROUPS}``; scalars are None before any update."""
        result: dict[str, Any] = {
            key: _finite_or_none(_group_then_mean({g: s[key] for g, s in self._scores.items()})) for key in self._KEYS
        }
        result[COUNT_IMAGES] = sum(len(s[PSNR_CLAMPED]) for s in self._scores.values())
        result[COUNT_GROUPS] = len(self._scores)
        return result

    def compute_per_group(self) -> dict[str, dict[str, Any]]:
        """``{group: {PSNR_CLAMPED, SSIM_GAUSSIAN11, COUNT_IMAGES}}``."""
        return {
            group: {
                **{key: _finite_or_none(_mean(scores[key])) for key in self._KEYS},
                COUNT_IMAGES: len(scores[PSNR_CLAMPED]),
            }
            for group, scores in self._scores.items()
        }


# ----------------------------------------------------------------------------------------------------------------
# Depth


def depth_errors(pred: Tensor, gt: Tensor) -> dict[str, float] | None:
    """One image's depth protocols (:data:`DEPTH_ABS_REL`, :data:`DEPTH_RMSE`).

    Args:
        pred: ``[h, w]`` rendered depth in metres, one value per cell of ``H / h`` pixels a side.
        gt: ``[H, W]`` ground-truth depth in metres, 0 (or not finite) where unknown.

    Returns:
        The two values, or None when no cell has ground-truth depth at every pixel.

    Raises:
        NonFiniteError: the rendered depth holds NaN or Inf.
        ValueError: ``H, W`` is not a whole multiple of ``h, w``.
    """
    pred = pred.detach().to("cpu", torch.float64)
    gt = gt.detach().to("cpu", torch.float64)
    if pred.dim() != 2 or gt.dim() != 2:
        raise ValueError(f"depth maps must be [h, w] and [H, W], got {list(pred.shape)} and {list(gt.shape)}")
    stride = gt.shape[0] // pred.shape[0]
    if stride < 1 or tuple(gt.shape) != (pred.shape[0] * stride, pred.shape[1] * stride):
        raise ValueError(
            f"ground-truth depth {list(gt.shape)} is not a whole multiple of the rendered {list(pred.shape)}"
        )
    if not all_finite(pred):
        raise NonFiniteError("rendered depth contains NaN or Inf values")
    known = torch.isfinite(gt) & (gt > 0)
    cells = torch.nn.functional.avg_pool2d(torch.where(known, gt, 0.0)[None, None], stride)[0, 0]
    covered = torch.nn.functional.avg_pool2d(known.to(torch.float64)[None, None], stride)[0, 0] == 1.0
    if not bool(covered.any()):
        return None
    truth, rendered = cells[covered], pred[covered]
    return {
        DEPTH_ABS_REL: float(((rendered - truth).abs() / truth).mean()),
        DEPTH_RMSE: float((rendered - truth).square().mean().sqrt()),
    }


class DepthAccumulator:
    """Collects per-image depth errors and averages them within groups, then over groups."""

    _KEYS = (DEPTH_ABS_REL, DEPTH_RMSE)

    def __init__(self) -> None:
        self._scores: dict[str, dict[str, list[float]]] = {}

    def add_scores(self, scores: dict[str, float], group: str = DEFAULT_GROUP) -> None:
        """Add one image's :func:`depth_errors`."""
        bucket = self._scores.setdefault(group, {key: [] for key in self._KEYS})
        for key in self._KEYS:
            bucket[key].append(scores[key])

    def compute(self) -> dict[str, Any]:
        """``{DEPTH_ABS_REL, DEPTH_RMSE, COUNT_IMAGES_WITH_DEPTH}``, and :data:`DEPTH_UNAVAILABLE_REASON` when no image
        had ground-truth depth."""
        result: dict[str, Any] = {
            key: _group_then_mean({g: s[key] for g, s in self._scores.items()}) for key in self._KEYS
        }
        result[COUNT_IMAGES_WITH_DEPTH] = sum(len(s[DEPTH_ABS_REL]) for s in self._scores.values())
        if not result[COUNT_IMAGES_WITH_DEPTH]:
            result[DEPTH_UNAVAILABLE_REASON] = "no evaluated frame has ground-truth depth"
        return result


def lpips_vgg_status() -> dict[str, Any]:
    """Report LPIPS (VGG) as unavailable, with the reason; gpnerf-core never emits an LPIPS number it cannot compute.

    Returns:
        ``{LPIPS_VGG: None, LPIPS_VGG_REASON: "..."}``.
    """
    if importlib.util.find_spec("lpips") is None:
        reason = (
            "the 'lpips' package is not installed (it requires torchvision, and its VGG-16 backbone weights "
            "are downloaded at run time)"
        )
    else:
        reason = (
            "gpnerf-core does not run LPIPS: its VGG-16 backbone weights are fetched from the internet at run "
            "time, so results would depend on network access"
        )
    return {LPIPS_VGG: None, LPIPS_VGG_REASON: reason}
