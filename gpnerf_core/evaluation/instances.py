"""Instance segmentation: masks from ids, Hungarian matching, the paper's matched AP and COCO mask AP.

Every id present in a ground-truth frame is an instance, background (0) included, as in the reference's
``InsEvaluator`` (REFERENCE.md §1(c), §6); both protocols below use that ground-truth set.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

AP_MATCHED_THRESHOLDS = (0.5, 0.75, 0.8, 0.85, 0.9, 0.95)
"""IoU thresholds of the paper's matched AP (a match counts when IoU > threshold)."""

AP_MATCHED_75 = "instance/ap_matched@0.75"
"""The paper's instance AP (Table 2). Per image: every GT id is an instance; each predicted slot's mask is the set of
pixels whose most probable slot it is, its confidence the median of those pixels' top probability. GT and predicted
masks are matched one-to-one (Hungarian, cost = fraction of mismatched pixels + 1 - IoU); an unmatched GT gets an
empty mask with confidence 0. The GT's matched IoUs sorted by confidence give precision cumsum(TP)/rank and recall
cumsum(TP)/#GT with TP = IoU > 0.75; AP is the area under the monotone precision envelope (all points). Extra
predictions are never false positives. Averaged within groups (scenes), then over groups."""

AP_MATCHED = "instance/ap_matched"
"""``{threshold: AP}`` of the same protocol at every threshold of ``AP_MATCHED_THRESHOLDS``."""

COCO_AP = "instance/coco_mask_ap"
"""COCO mask AP over IoU 0.50:0.05:0.95 (pycocotools ``COCOeval``, iouType ``segm``, one class-agnostic category,
up to 100 detections per image), every evaluated view an image, every non-empty predicted mask a detection scored by
its confidence (as above), every GT id an instance (background included)."""

COCO_AP50 = "instance/coco_mask_ap50"
"""COCO mask AP at IoU 0.50 (same evaluation as ``COCO_AP``)."""

COCO_AP75 = "instance/coco_mask_ap75"
"""COCO mask AP at IoU 0.75 (same evaluation as ``COCO_AP``)."""

COUNT_INSTANCES = "count/gt_instances"
"""Ground-truth instances over the evaluated views."""

AP_KEYS = (AP_MATCHED_75, AP_MATCHED, COCO_AP, COCO_AP50, COCO_AP75)
"""The instance protocols of an instance head (None, with ``labels/unavailable_reason``, on scenes without labels)."""


def instance_masks(ids: Tensor) -> tuple[Tensor, Tensor]:
    """Masks of every id present: ``[H, W]`` integer ids -> (ids ``[G]`` ascending, masks ``[G, H * W]`` bool)."""
    flat = ids.reshape(-1).long()
    unique, inverse = torch.unique(flat, return_inverse=True)
    masks = torch.zeros(len(unique), flat.numel(), dtype=torch.bool, device=ids.device)
    masks[inverse, torch.arange(flat.numel(), device=ids.device)] = True
    return unique, masks


def hungarian(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost one-to-one assignment of rows to columns (scipy); ``min(rows, cols)`` pairs ``(rows, cols)``."""
    from scipy.optimize import linear_sum_assignment  # here: importing it costs every command 0.5 s at start

    rows, cols = linear_sum_assignment(np.nan_to_num(np.asarray(cost, dtype=np.float64), nan=1e9, posinf=1e9))
    return rows, cols


SLOT_ACTIVATIONS = ("softmax", "sigmoid")


def slot_probabilities(logits: Tensor, activation: str = "softmax") -> Tensor:
    """``[K + 1, ...]`` instance scores -> ``[K, ...]`` slot probabilities: a softmax over the channels (an instance
    head's) or each channel's sigmoid (DM-NeRF's), the last ("no instance") channel dropped either way."""
    if activation not in SLOT_ACTIVATIONS:
        raise ValueError(f"slot activation {activation!r}; expected one of: {', '.join(SLOT_ACTIVATIONS)}")
    scores = logits.float()
    return (torch.softmax(scores, dim=0) if activation == "softmax" else torch.sigmoid(scores))[:-1]


def slot_predictions(logits: Tensor, activation: str = "softmax") -> tuple[Tensor, Tensor]:
    """Hard instance slots of an instance model's output.

    Args:
        logits: ``[K + 1, H, W]``; slot probabilities by ``activation`` (``slot_probabilities``), the last channel,
            "no instance", dropped (as the reference and DM-NeRF do), so every pixel goes to its most probable of the
            K slots.

    Returns:
        ``(slots [H, W] int64 in [0, K), confidence [K])``: a slot's confidence is the median of its pixels' top slot
        probability, 0 for a slot no pixel chose.
    """
    probabilities = slot_probabilities(logits, activation)
    top, slots = probabilities.max(dim=0)
    confidence = torch.zeros(probabilities.shape[0])
    for k in torch.unique(slots).tolist():
        confidence[k] = top[slots == k].median().cpu()
    return slots, confidence


def match_masks(gt: Tensor, pred: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match hard masks one-to-one.

    Args:
        gt: ``[G, P]`` bool; pred: ``[N, P]`` bool.

    Returns:
        ``(iou [G, N], gt_rows, pred_cols)`` of the matching that minimises mismatched-pixel fraction + 1 - IoU.
    """
    gt_f, pred_f = gt.double(), pred.double()
    inter = gt_f @ pred_f.T
    union = gt_f.sum(1, keepdim=True) + pred_f.sum(1)[None] - inter
    iou = torch.where(union > 0, inter / union.clamp(min=1), torch.zeros_like(inter))
    mismatch = (union - inter) / max(gt.shape[1], 1)
    rows, cols = hungarian((mismatch + 1.0 - iou).cpu().numpy())
    return iou.cpu().numpy(), rows, cols


def precision_envelope_ap(scores: np.ndarray, hits: np.ndarray, num_gt: int) -> float:
    """Area under the monotone precision envelope of the ranked hits (all-point interpolation).

    Args:
        scores: ``[M]`` confidences; hits: ``[M]`` bool, the entry is a true positive; num_gt: recall's denominator.
    """
    if num_gt == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(hits[order].astype(np.float64))
    precision = tp / np.arange(1, len(tp) + 1)
    recall = tp / num_gt
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.nonzero(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


def matched_ap(
    pred_ids: Tensor, confidence: Tensor, gt_ids: Tensor, thresholds: Sequence[float] = AP_MATCHED_THRESHOLDS
) -> tuple[dict[float, float], dict[int, int]]:
    """The paper's matched AP of one image (see ``AP_MATCHED_75``).

    Args:
        pred_ids: ``[H, W]`` predicted instance ids in ``[0, N)``; confidence: ``[N]``.
        gt_ids: ``[H, W]`` ground-truth ids.

    Returns:
        ``({threshold: AP}, {predicted id: matched GT id})``.
    """
    if pred_ids.shape != gt_ids.shape:
        raise ValueError(f"predicted instances {tuple(pred_ids.shape)} and GT {tuple(gt_ids.shape)} differ in size")
    ids, gt = instance_masks(gt_ids.cpu())
    num_pred = int(confidence.numel())
    pred = torch.zeros(num_pred, pred_ids.numel(), dtype=torch.bool)
    flat = pred_ids.reshape(-1).long().cpu()
    pred[flat, torch.arange(flat.numel())] = True
    iou, rows, cols = match_masks(gt, pred)
    matched_iou = np.zeros(len(ids))
    scores = np.zeros(len(ids))
    conf = confidence.double().cpu().numpy()
    for r, c in zip(rows, cols):
        if pred[c].any():
            matched_iou[r], scores[r] = iou[r, c], conf[c]
    aps = {float(t): precision_envelope_ap(scores, matched_iou > t, len(ids)) for t in thresholds}
    pairing = {int(c): int(ids[r]) for r, c in zip(rows, cols) if pred[c].any()}
    return aps, pairing


def connected_component_instances(classes: Tensor, top_probability: Tensor) -> tuple[Tensor, Tensor]:
    """The trivial baseline: every 8-connected region of one predicted class is an instance.

    Args:
        classes: ``[H, W]`` predicted class ids; top_probability: ``[H, W]`` the softmax probability of that class.

    Returns:
        ``(ids [H, W] int64 in [0, N), confidence [N])``, confidence = mean top probability of the component.
    """
    from scipy import ndimage

    labels = classes.cpu().numpy()
    ids = np.zeros(labels.shape, dtype=np.int64)
    count = 0
    for value in np.unique(labels):
        components, found = ndimage.label(labels == value, structure=np.ones((3, 3), dtype=bool))
        inside = components > 0
        ids[inside] = components[inside] - 1 + count
        count += found
    ids_t = torch.from_numpy(ids)
    flat = ids_t.reshape(-1)
    sums = torch.zeros(count, dtype=torch.float64).index_add_(0, flat, top_probability.double().cpu().reshape(-1))
    sizes = torch.bincount(flat, minlength=count).clamp(min=1)
    return ids_t, (sums / sizes).float()


# ---- COCO mask AP ------------------------------------------------------------------------------------------------


def encode_masks(ids: Tensor, keep: Sequence[int] | None = None) -> list[tuple[int, dict[str, Any]]]:
    """Run-length encodings (pycocotools) of the mask of every id present in ``[H, W]`` ``ids`` (or of ``keep``)."""
    from pycocotools import mask as mask_utils

    array = ids.cpu().numpy()
    present = np.unique(array).tolist() if keep is None else list(keep)
    out = []
    for value in present:
        mask = np.asfortranarray((array == value).astype(np.uint8))
        if mask.any():
            out.append((int(value), mask_utils.encode(mask)))
    return out


@dataclass
class CocoImage:
    """One view for the COCO evaluation: its GT masks and the scored predicted masks (RLE), picklable."""

    height: int
    width: int
    gt: list[dict[str, Any]]
    detections: list[tuple[dict[str, Any], float]] = field(default_factory=list)


def coco_image(pred_ids: Tensor, confidence: Tensor, gt_ids: Tensor) -> CocoImage:
    """The COCO record of one view from its predicted ids ``[H, W]``, their confidences ``[N]`` and GT ids."""
    height, width = (int(s) for s in gt_ids.shape)
    gt = [rle for _, rle in encode_masks(gt_ids)]
    detections = [(rle, float(confidence[k])) for k, rle in encode_masks(pred_ids)]
    return CocoImage(height, width, gt, detections)


def coco_mask_ap(images: Sequence[CocoImage]) -> dict[str, float | None]:
    """``{COCO_AP, COCO_AP50, COCO_AP75}`` over ``images`` (pycocotools; its printout suppressed)."""
    from pycocotools import mask as mask_utils
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt_annotations, detections = [], []
    for image_id, image in enumerate(images, start=1):
        for rle in image.gt:
            gt_annotations.append(
                {
                    "id": len(gt_annotations) + 1,
                    "image_id": image_id,
                    "category_id": 1,
                    "segmentation": rle,
                    "area": float(mask_utils.area(rle)),
                    "bbox": mask_utils.toBbox(rle).tolist(),
                    "iscrowd": 0,
                }
            )
        for rle, score in image.detections:
            detections.append({"image_id": image_id, "category_id": 1, "segmentation": rle, "score": score})
    keys = (COCO_AP, COCO_AP50, COCO_AP75)
    if not gt_annotations:
        return dict.fromkeys(keys)
    if not detections:
        return dict.fromkeys(keys, 0.0)
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO()
        coco.dataset = {
            "images": [{"id": i, "height": im.height, "width": im.width} for i, im in enumerate(images, start=1)],
            "annotations": gt_annotations,
            "categories": [{"id": 1, "name": "instance"}],
        }
        coco.createIndex()
        evaluation = COCOeval(coco, coco.loadRes(detections), iouType="segm")
        evaluation.evaluate()
        evaluation.accumulate()
        evaluation.summarize()
    stats = evaluation.stats
    return {key: max(float(value), 0.0) for key, value in zip(keys, stats[:3])}


# ---- per view and per split --------------------------------------------------------------------------------------


@dataclass
class InstanceRecord:
    """What the summary needs from one view's instance prediction: matched AP per threshold and its COCO record."""

    ap: dict[float, float]
    coco: CocoImage
    gt_instances: int


def instance_record(pred_ids: Tensor, confidence: Tensor, gt_ids: Tensor) -> tuple[InstanceRecord, dict[int, int]]:
    """Score one view's instances; also returns ``{predicted id: matched GT id}`` for its picture."""
    aps, pairing = matched_ap(pred_ids, confidence, gt_ids)
    coco = coco_image(pred_ids, confidence, gt_ids)
    record = InstanceRecord(ap=aps, coco=coco, gt_instances=len(torch.unique(gt_ids)))
    return record, pairing


class InstanceAccumulator:
    """Matched AP averaged within groups (scenes) then over groups; COCO mask AP over every added view."""

    def __init__(self) -> None:
        self._groups: dict[str, list[dict[float, float]]] = {}
        self._coco: list[CocoImage] = []
        self._instances = 0

    def add(self, record: InstanceRecord, group: str) -> None:
        self._groups.setdefault(group, []).append(record.ap)
        self._coco.append(record.coco)
        self._instances += record.gt_instances

    def compute(self) -> dict[str, Any]:
        """``{AP_MATCHED_75, AP_MATCHED, COCO_AP, COCO_AP50, COCO_AP75, COUNT_INSTANCES}`` (None without views)."""
        if not self._coco:
            return {}
        by_threshold = {}
        for threshold in AP_MATCHED_THRESHOLDS:
            group_means = [float(np.nanmean([ap[threshold] for ap in aps])) for aps in self._groups.values()]
            by_threshold[str(threshold)] = float(np.mean(group_means))
        return {
            AP_MATCHED_75: by_threshold["0.75"],
            AP_MATCHED: by_threshold,
            **coco_mask_ap(self._coco),
            COUNT_INSTANCES: self._instances,
        }
