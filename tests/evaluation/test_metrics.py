"""Metrics against hand-computed values."""

from __future__ import annotations

import json
import math

import kornia
import numpy as np
import pytest
import torch

from gpnerf_core.errors import NonFiniteError
from gpnerf_core.evaluation import metrics as m

IGNORE = 255

# Hand example (K = 3): pairs (gt, pred) = (0,0) (0,1) (1,1) (1,2) (2,2), and one ignored pixel predicted 0.
TARGET = torch.tensor([[0, 0, 1], [1, 2, IGNORE]])
PRED = torch.tensor([[0, 1, 1], [2, 2, 0]])


def test_confusion_matrix_hand_example():
    confusion = m.confusion_matrix(PRED, TARGET, 3, IGNORE)
    assert confusion.dtype == torch.int64
    assert confusion.tolist() == [[1, 1, 0], [0, 1, 1], [0, 0, 1]]


def test_confusion_matrix_accepts_numpy_and_no_ignore():
    confusion = m.confusion_matrix(np.array([1, 1, 0]), np.array([1, 0, 0]), 2)
    assert confusion.tolist() == [[1, 1], [0, 1]]


def test_per_image_scores_hand_values():
    scores = m.image_segmentation_metrics(PRED, TARGET, 3, IGNORE)
    # IoU: class 0 = 1/2, class 1 = 1/3, class 2 = 1/2.
    assert scores[m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx((0.5 + 1 / 3 + 0.5) / 3)
    assert scores[m.ACC_IMAGE_TOTAL] == pytest.approx(3 / 5)
    # Recall: 1/2, 1/2, 1.
    assert scores[m.ACC_IMAGE_CLASS_MEAN_PRESENT] == pytest.approx(2 / 3)


def test_class_predicted_but_absent_from_gt_only_hurts_the_true_class():
    target = torch.tensor([0, 0, 0, 1])
    pred = torch.tensor([0, 0, 2, 1])
    scores = m.image_segmentation_metrics(pred, target, 3)
    # Present classes {0, 1}: IoU0 = TP 2 / (GT 3 + pred 2 - TP 2) = 2/3 (the pixel lost to class 2 is its FN),
    # IoU1 = 1; class 2 is not averaged.
    assert scores[m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx((2 / 3 + 1) / 2)
    # The dataset protocol counts class 2 (it was predicted) with IoU 0.
    dataset = m.dataset_scores_from_confusion(m.confusion_matrix(pred, target, 3))
    assert dataset[m.MIOU_DATASET] == pytest.approx((2 / 3 + 1 + 0) / 3)
    assert dataset[m.IOU_DATASET_PER_CLASS] == pytest.approx([2 / 3, 1.0, 0.0])


def test_ignored_pixels_are_dropped_whatever_is_predicted_there():
    target = torch.tensor([[0, 1, IGNORE, IGNORE]])
    pred_a = torch.tensor([[0, 1, 0, 1]])
    pred_b = torch.tensor([[0, 1, 1, 1]])
    assert m.confusion_matrix(pred_a, target, 2, IGNORE).tolist() == [[1, 0], [0, 1]]
    assert m.image_segmentation_metrics(pred_b, target, 2, IGNORE)[m.MIOU_IMAGE_MEAN_PRESENT] == 1.0


def test_image_without_valid_gt_is_excluded_and_counted():
    acc = m.SegmentationAccumulator(2, IGNORE)
    assert acc.update(torch.tensor([[0, 0]]), torch.tensor([[0, 0]]), "s") is not None
    assert acc.update(torch.tensor([[1, 1]]), torch.full((1, 2), IGNORE), "s") is None
    result = acc.compute()
    assert result[m.MIOU_IMAGE_MEAN_PRESENT] == 1.0
    assert result[m.COUNT_IMAGES] == 1
    assert result[m.COUNT_IMAGES_WITHOUT_VALID_GT] == 1


def test_dataset_miou_excludes_classes_absent_from_gt_and_prediction():
    acc = m.SegmentationAccumulator(5, IGNORE)
    acc.update(torch.tensor([0, 1, 2, 2]), torch.tensor([0, 1, 2, 1]))
    result = acc.compute()
    # IoU0 = 1, IoU1 = 1/2, IoU2 = 1/2; classes 3 and 4 never appear and are not scored as 1 (nor 0).
    assert result[m.IOU_DATASET_PER_CLASS] == [1.0, 0.5, 0.5, None, None]
    assert result[m.MIOU_DATASET] == pytest.approx(2 / 3)
    assert result[m.ACC_TOTAL] == pytest.approx(3 / 4)
    assert result[m.ACC_CLASS_MEAN] == pytest.approx((1 + 0.5 + 1) / 3)


def test_dataset_level_differs_from_per_image_on_pooled_confusion():
    acc = m.SegmentationAccumulator(2)
    acc.update(torch.tensor([0, 0, 0, 0]), torch.tensor([0, 0, 0, 0]))  # per-image mIoU 1
    acc.update(torch.tensor([0, 1]), torch.tensor([1, 1]))  # class 1 only: IoU1 = 1/2
    result = acc.compute()
    assert result[m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx((1 + 0.5) / 2)
    # Pooled: cm = [[4, 0], [1, 1]] -> IoU0 = 4/5, IoU1 = 1/2.
    assert acc.confusion.tolist() == [[4, 0], [1, 1]]
    assert result[m.MIOU_DATASET] == pytest.approx((0.8 + 0.5) / 2)
    assert result[m.ACC_TOTAL] == pytest.approx(5 / 6)
    assert result[m.ACC_IMAGE_TOTAL] == pytest.approx((1 + 0.5) / 2)


def test_group_then_mean_is_not_image_mean():
    perfect = (torch.tensor([0, 0]), torch.tensor([0, 0]))  # mIoU 1
    half = (torch.tensor([0, 1]), torch.tensor([0, 0]))  # only class 0 present: IoU 1/2
    acc = m.SegmentationAccumulator(2)
    acc.update(*perfect, group="scene_a")
    for _ in range(3):
        acc.update(*half, group="scene_b")
    result = acc.compute()
    image_mean = (1 + 3 * 0.5) / 4
    group_mean = (1 + 0.5) / 2
    assert image_mean != pytest.approx(group_mean)
    assert result[m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx(group_mean)
    assert result[m.COUNT_IMAGES] == 4 and result[m.COUNT_GROUPS] == 2
    per_group = acc.compute_per_group()
    assert per_group["scene_a"][m.MIOU_IMAGE_MEAN_PRESENT] == 1.0
    assert per_group["scene_b"][m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx(0.5)
    assert per_group["scene_b"][m.COUNT_IMAGES] == 3


def test_compute_is_json_ready_plain_python():
    acc = m.SegmentationAccumulator(3, IGNORE)
    acc.update(PRED, TARGET, "a")
    result = acc.compute()
    json.dumps(result, allow_nan=False)
    json.dumps(acc.compute_per_group(), allow_nan=False)
    assert all(type(v) in (float, int, list) for v in result.values())
    empty = m.SegmentationAccumulator(3).compute()
    assert empty[m.MIOU_IMAGE_MEAN_PRESENT] is None and empty[m.MIOU_DATASET] is None
    json.dumps(empty, allow_nan=False)


@pytest.mark.parametrize("bad_value", [3, -1])
def test_out_of_range_prediction_raises_naming_the_value(bad_value):
    pred = PRED.clone()
    pred[1, 2] = bad_value  # even at an ignored GT pixel
    with pytest.raises(ValueError, match=rf"predicted class {bad_value}\b"):
        m.confusion_matrix(pred, TARGET, 3, IGNORE)


def test_bad_target_dtype_and_shape_raise():
    with pytest.raises(ValueError, match="ground-truth label 7"):
        m.confusion_matrix(torch.tensor([0]), torch.tensor([7]), 3, IGNORE)
    with pytest.raises(ValueError, match="integer"):
        m.confusion_matrix(torch.tensor([0.0]), torch.tensor([0]), 3)
    with pytest.raises(ValueError, match="shape"):
        m.confusion_matrix(torch.tensor([0, 1]), torch.tensor([0]), 3)


def test_constant_prediction_and_class_counts():
    targets = [torch.tensor([[0, 0, 1, IGNORE]]), torch.tensor([[2, 2, 2, 0]])]
    counts = m.class_pixel_counts(targets, 3, IGNORE)
    assert counts == [3, 1, 3]
    result = m.constant_prediction_metrics([(targets[0], "a"), (targets[1], "b")], 0, 3, IGNORE)
    # Image a: IoU0 = 2/3, IoU1 = 0 -> 1/3. Image b: IoU0 = 1/4, IoU2 = 0 -> 1/8.
    assert result[m.MIOU_IMAGE_MEAN_PRESENT] == pytest.approx((1 / 3 + 1 / 8) / 2)
    # Pooled: class 0 -> TP 3, predicted 7 -> IoU 3/7; classes 1, 2 IoU 0.
    assert result[m.MIOU_DATASET] == pytest.approx(3 / 7 / 3)
    assert result[m.ACC_TOTAL] == pytest.approx(3 / 7)
    with pytest.raises(ValueError, match="constant class 3"):
        m.constant_prediction_metrics([(targets[0], "a")], 3, 3, IGNORE)


# ---------------------------------------------------------------------------------------------------------------
# Image quality


def test_psnr_of_known_mse():
    gt = np.full((8, 8, 3), 0.5)
    assert m.psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)
    assert m.psnr(torch.full((8, 8, 3), 0.51), torch.full((8, 8, 3), 0.5)) == pytest.approx(40.0, abs=1e-4)
    assert m.psnr(gt, gt) == math.inf


def test_psnr_clamps_prediction_to_unit_range():
    gt = np.full((4, 4, 3), 0.9)
    pred = np.full((4, 4, 3), 1.3)  # unbounded GNT colour
    assert m.psnr(pred, gt) == pytest.approx(20.0)  # clamped error 0.1
    assert m.psnr(pred, gt, clamp=False) == pytest.approx(-10 * math.log10(0.16))


def test_psnr_is_skimages_to_the_bit():
    from skimage.metrics import peak_signal_noise_ratio

    generator = torch.Generator().manual_seed(3)
    for shape in ((5, 7, 3), (32, 48, 3), (96, 128, 3)):
        gt, pred = torch.rand(*shape, generator=generator), torch.rand(*shape, generator=generator) * 1.2 - 0.1
        for clamp in (True, False):
            a, b = (np.clip(x.double().numpy(), 0, 1) if clamp else x.double().numpy() for x in (pred, gt))
            assert m.psnr(pred, gt, clamp=clamp) == float(peak_signal_noise_ratio(b, a, data_range=1.0))


def test_ssim_identity_clamp_and_reference():
    generator = torch.Generator().manual_seed(0)
    gt = torch.rand(24, 28, 3, generator=generator)
    assert m.ssim(gt, gt) == pytest.approx(1.0)
    assert m.ssim(gt * 1.5 - 0.25, gt.mul(1.5).sub(0.25).clamp(0, 1)) == pytest.approx(1.0)
    noisy = (gt + 0.1 * torch.randn(24, 28, 3, generator=generator)).clamp(0, 1)
    value = m.ssim(noisy, gt)
    # Independent implementation: kornia's Gaussian 11x11 SSIM on the valid region.
    reference = kornia.metrics.ssim(
        noisy.permute(2, 0, 1)[None].double(), gt.permute(2, 0, 1)[None].double(), 11, max_val=1.0, padding="valid"
    ).mean()
    assert 0.5 < value < 0.99
    assert value == pytest.approx(float(reference), abs=1e-6)


def test_image_metrics_reject_bad_input():
    with pytest.raises(ValueError, match="at least 11"):
        m.ssim(np.zeros((8, 20, 3)), np.zeros((8, 20, 3)))
    with pytest.raises(ValueError, match="RGB"):
        m.psnr(np.zeros((8, 8)), np.zeros((8, 8)))
    with pytest.raises(NonFiniteError, match="pred"):
        m.psnr(np.full((4, 4, 3), np.nan), np.zeros((4, 4, 3)))


def test_image_quality_accumulator_group_then_mean():
    gt = np.full((12, 12, 3), 0.5)
    acc = m.ImageQualityAccumulator()
    acc.update(gt + 0.1, gt, "a")  # 20 dB
    acc.update(gt + 0.1, gt, "b")  # 20 dB
    scores = acc.update(gt + 0.01, gt, "b")  # 40 dB
    assert scores[m.PSNR_CLAMPED] == pytest.approx(40.0)
    result = acc.compute()
    assert result[m.PSNR_CLAMPED] == pytest.approx((20 + 30) / 2)
    assert result[m.COUNT_IMAGES] == 3 and result[m.COUNT_GROUPS] == 2
    assert acc.compute_per_group()["b"][m.PSNR_CLAMPED] == pytest.approx(30.0)
    assert 0 < result[m.SSIM_GAUSSIAN11] <= 1
    json.dumps(result, allow_nan=False)


def test_image_quality_infinite_psnr_is_reported_as_none():
    gt = np.full((12, 12, 3), 0.5)
    acc = m.ImageQualityAccumulator()
    acc.update(gt, gt)
    result = acc.compute()
    assert result[m.PSNR_CLAMPED] is None
    assert result[m.SSIM_GAUSSIAN11] == pytest.approx(1.0)
    assert m.ImageQualityAccumulator().compute()[m.PSNR_CLAMPED] is None


def test_lpips_reports_unavailable_with_reason(monkeypatch):
    status = m.lpips_vgg_status()
    assert status[m.LPIPS_VGG] is None
    assert isinstance(status[m.LPIPS_VGG_REASON], str) and status[m.LPIPS_VGG_REASON]
    monkeypatch.setattr(m.importlib.util, "find_spec", lambda name: None)
    assert "not installed" in m.lpips_vgg_status()[m.LPIPS_VGG_REASON]
