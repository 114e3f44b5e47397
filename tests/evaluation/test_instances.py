"""Instance segmentation: the Hungarian loss, the matched and COCO APs, the baseline, the head and the CLI path."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import instances as I
from gpnerf_core.evaluation.visualize import colorize_instances
from gpnerf_plugins.losses.instance import hungarian_instance_loss

TINY = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.num_train_scenes=1", "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4",
    "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "threads=1", "eval.save_images=1",
    "head.channels=16", "head.norm_groups=4",
]


def three_objects() -> torch.Tensor:
    """``[8, 10]`` ids: background 0, a 3x3 box (id 7), a 2x4 box (id 3), a 1x2 box (id 12)."""
    ids = torch.zeros(8, 10, dtype=torch.long)
    ids[1:4, 1:4] = 7
    ids[5:7, 2:6] = 3
    ids[2, 7:9] = 12
    return ids


def logits_for(ids: torch.Tensor, slot_of: dict[int, int], slots: int, scale: float = 20.0) -> torch.Tensor:
    """``[slots + 1, H, W]`` logits that put each pixel in ``slot_of[its id]`` with high confidence."""
    logits = torch.zeros(slots + 1, *ids.shape)
    for value, slot in slot_of.items():
        logits[slot][ids == value] = scale
    return logits


# ---- the Hungarian loss ----------------------------------------------------------------------------------------


def test_the_loss_is_near_zero_for_a_confident_correct_prediction_in_any_slot_order():
    ids = three_objects()
    right = hungarian_instance_loss(logits_for(ids, {0: 0, 7: 1, 3: 2, 12: 3}, slots=6), ids)
    permuted = hungarian_instance_loss(logits_for(ids, {0: 5, 7: 2, 3: 0, 12: 4}, slots=6), ids)
    for parts in (right, permuted):
        assert parts["bce"] < 1e-5 and parts["iou"] < 1e-5 and parts["unmatched"] < 1e-5
    wrong = hungarian_instance_loss(logits_for(ids, {0: 0, 7: 0, 3: 1, 12: 1}, slots=6), ids)  # objects merged
    assert wrong["iou"] > 0.3 and wrong["bce"] > 0.5


def test_the_loss_matches_its_definition_and_has_gradients():
    torch.manual_seed(0)
    ids = three_objects()
    logits = torch.randn(6, *ids.shape, requires_grad=True)
    parts = hungarian_instance_loss(logits, ids)
    # Brute force: every injective assignment of the 4 GT masks to the 5 slots.
    from itertools import permutations

    probs = torch.softmax(logits.detach().double(), 0)[:-1].reshape(5, -1).clamp(1e-6, 1 - 1e-6)
    gt = torch.stack([(ids == v).reshape(-1).double() for v in torch.unique(ids)])
    bce = -(gt[:, None] * probs[None].log() + (1 - gt[:, None]) * (1 - probs[None]).log()).mean(-1)
    soft = torch.softmax(logits.detach().double(), 0)[:-1].reshape(5, -1)
    iou = (gt @ soft.T) / (gt.sum(1, keepdim=True) + soft.sum(1)[None] - gt @ soft.T)
    cost = bce + 1 - iou
    best = min(permutations(range(5), 4), key=lambda cols: sum(cost[g, c] for g, c in enumerate(cols)))
    unmatched = [k for k in range(5) if k not in best]
    assert parts["bce"].item() == pytest.approx(float(np.mean([bce[g, c] for g, c in enumerate(best)])), rel=1e-4)
    assert parts["iou"].item() == pytest.approx(float(np.mean([1 - iou[g, c] for g, c in enumerate(best)])), rel=1e-4)
    assert parts["unmatched"].item() == pytest.approx(float(soft[unmatched].mean()), rel=1e-4)
    sum(parts.values()).backward()
    assert torch.isfinite(logits.grad).all() and logits.grad.abs().sum() > 0


def test_a_head_collapsed_into_one_saturated_slot_still_gets_gradients():
    # One slot near 1 everywhere, the others near 0: with BCE on clamped probabilities the gradient vanished and a
    # training run stayed at this loss for 600 steps (seed 2 of layout_00). log_softmax keeps it alive.
    ids = three_objects()
    logits = torch.full((6, *ids.shape), -30.0)
    logits[0] = 30.0
    logits.requires_grad_(True)
    sum(hungarian_instance_loss(logits, ids).values()).backward()
    for value in (7, 3, 12):  # each object's pixels pull some other slot up
        pulled = logits.grad[1:5][:, ids == value]
        assert pulled.min() < -0.01 / ids.numel()


def test_more_instances_than_slots_is_one_line_naming_head_slots():
    ids = three_objects()
    with pytest.raises(ConfigError, match=r"4 instance ids .* head has 3 slots; set head.slots >= 4"):
        hungarian_instance_loss(torch.zeros(4, *ids.shape), ids)


# ---- metrics -----------------------------------------------------------------------------------------------------


def test_matched_ap_is_one_for_a_perfect_prediction_and_extra_slots_are_not_false_positives():
    gt = three_objects()
    pred = gt.clone()
    pred[gt == 7], pred[gt == 3], pred[gt == 12], pred[gt == 0] = 1, 2, 3, 0
    pred[0, 0] = 4  # an extra one-pixel instance
    aps, pairing = I.matched_ap(pred, torch.tensor([0.9, 0.8, 0.7, 0.6, 0.99]), gt)
    assert pairing[1] == 7 and pairing[2] == 3 and pairing[3] == 12
    assert aps[0.5] == 1.0  # background loses one pixel of 61 to the extra instance: IoU 0.98
    assert aps[0.95] == 1.0


def test_matched_ap_counts_a_missed_instance_and_orders_by_confidence():
    gt = three_objects()
    pred = torch.zeros_like(gt)
    pred[gt == 7] = 1  # the 3x3 box found; the others merged into background (slot 0)
    aps, _ = I.matched_ap(pred, torch.tensor([0.5, 0.9]), gt)
    # GT ranked by confidence: box 7 (0.9, IoU 1), background (0.5, IoU 55/67 = 0.82), two GTs unmatched (0).
    assert aps[0.75] == pytest.approx(0.5)  # precision 1 up to recall 2/4
    assert aps[0.9] == pytest.approx(0.25)


def test_precision_envelope_by_hand():
    # Ranked hits: yes, no, yes with 4 GT: precision 1, 1/2, 2/3; recall 1/4, 1/4, 1/2 -> 1/4 * 1 + 1/4 * 2/3.
    ap = I.precision_envelope_ap(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), num_gt=4)
    assert ap == pytest.approx(0.25 + 0.25 * 2 / 3)


def test_coco_mask_ap_is_one_for_perfect_masks_and_zero_without_detections():
    gt = three_objects()
    perfect = I.coco_mask_ap([I.coco_image(gt, torch.ones(13), gt)])
    assert perfect[I.COCO_AP] == pytest.approx(1.0) and perfect[I.COCO_AP75] == pytest.approx(1.0)
    empty = I.CocoImage(8, 10, [rle for _, rle in I.encode_masks(gt)], [])
    assert I.coco_mask_ap([empty]) == {I.COCO_AP: 0.0, I.COCO_AP50: 0.0, I.COCO_AP75: 0.0}
    merged = torch.where(gt == 12, torch.zeros_like(gt), gt)  # the smallest object missed
    partial = I.coco_mask_ap([I.coco_image(merged, torch.ones(13), gt)])
    assert 0.5 < partial[I.COCO_AP50] < 1.0


def test_connected_components_split_one_class_into_its_regions():
    classes = torch.zeros(6, 9, dtype=torch.long)
    classes[1:3, 1:3] = 2
    classes[1:3, 6:8] = 2  # the same class, not touching
    classes[4, 4] = 1
    top = torch.full((6, 9), 0.5)
    top[1:3, 1:3] = 0.9
    ids, confidence = I.connected_component_instances(classes, top)
    assert len(confidence) == 4  # background, two boxes, one pixel
    assert len(torch.unique(ids[1:3, 1:3])) == 1 and ids[1, 1] != ids[1, 6]
    assert confidence[ids[1, 1]] == pytest.approx(0.9) and confidence[ids[1, 6]] == pytest.approx(0.5)


def test_slot_confidence_is_the_median_top_probability_and_the_last_channel_is_dropped():
    logits = torch.full((3, 1, 4), -10.0)
    logits[0, 0, :3] = torch.tensor([0.0, 1.0, 2.0])
    logits[1, 0, 3] = 5.0
    logits[2] = torch.tensor([1.0, 1.0, 1.0, 9.0])  # "no instance" is most probable at the last pixel, but is dropped
    slots, confidence = I.slot_predictions(logits)
    assert slots.tolist() == [[0, 0, 0, 1]]
    probabilities = torch.softmax(logits, dim=0)  # over all K + 1 channels, as the reference does
    assert confidence[0] == pytest.approx(float(probabilities[0, 0, 1]))  # the median of the slot's three pixels
    assert confidence[1] == pytest.approx(float(probabilities[1, 0, 3]))
    assert confidence[1] < 0.02


def test_instance_colours_are_stable_and_distinct():
    ids = torch.tensor([[0, 1, 2], [3, 1, 40]])
    picture = colorize_instances(ids)
    assert picture.shape == (2, 3, 3) and (picture[0, 1] == picture[1, 1]).all()
    assert len({tuple(c) for c in picture.reshape(-1, 3)}) == 5
    assert (colorize_instances(torch.tensor([[40]]))[0, 0] == picture[1, 2]).all()


# ---- head, loss set and their pairing ------------------------------------------------------------------------------


def test_the_instance_head_has_slots_plus_one_outputs():
    components = build_components(compose(["+head=instance", "+loss=instance", *TINY, "head.slots=9"]))
    assert components.model.head.num_outputs == 10 and components.model.head.predicts == "instances"
    assert components.loss.needs_instances and components.loss.head_predicts == "instances"
    assert set(components.loss.weights) == {"rgb", "instance", "sd"}


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["+head=instance", "+loss=dgs"], r"loss 'dgs' trains classes but head 'instance' predicts instances"),
        (["+head=unet", "+loss=instance"], r"loss 'instance' trains instances but head 'unet' predicts classes"),
        (["+head=instance", "+loss=instance", "loss.ce_weight=1"], r"loss.ce_weight=1.0: .* expected 0"),
        (["+head=instance", "+loss=instance", "head.slots=0"], r"head.slots=0: expected a positive"),
    ],
)
def test_mismatched_heads_and_losses_are_refused(overrides, message):
    with pytest.raises(ConfigError, match=message):
        build_components(compose([*overrides, *TINY]))


# ---- the command line ------------------------------------------------------------------------------------------------


def gpnerf(*args, cwd):
    env = dict(os.environ, GPNERF_CACHE=str(cwd / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def test_an_instance_run_reports_both_aps_and_draws_instances(tmp_path):
    done = gpnerf("run", "+head=instance", "+loss=instance", *TINY, "train.steps=3", "out_dir=inst", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "AP@0.75" in done.stdout and "COCO AP" in done.stdout
    metrics = json.loads((tmp_path / "inst" / "metrics.json").read_text())
    held_out = metrics["eval"]["train_heldout"]
    for key in (I.AP_MATCHED_75, I.COCO_AP, I.COCO_AP50, I.COCO_AP75):
        assert 0.0 <= held_out[key] <= 1.0
    assert set(held_out[I.AP_MATCHED]) == {str(t) for t in I.AP_MATCHED_THRESHOLDS}
    assert I.AP_MATCHED_75 in held_out["teacher_2d"] and "miou/image_mean_present" not in held_out
    pictures = sorted((tmp_path / "inst" / "images" / "train_heldout").glob("*_instances.png"))
    assert pictures and np.asarray(Image.open(pictures[0])).shape[-1] == 3
    checkpoint = tmp_path / "inst" / "checkpoints" / "step_0000003.pt"
    video = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=2", "out_dir=video", cwd=tmp_path)
    assert video.returncode == 0, video.stderr[-2000:]
    frame = np.asarray(Image.open(tmp_path / "video" / "frames" / "0001.png"))
    assert frame.shape[1] > 3 * 48  # rgb, depth and instances side by side


def test_a_semantic_run_scores_connected_components_as_the_instance_baseline(tmp_path):
    done = gpnerf("run", "+head=unet", "+loss=ce", *TINY[:-2], "train.steps=2", "out_dir=sem", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    metrics = json.loads((tmp_path / "sem" / "metrics.json").read_text())
    baseline = metrics["eval"]["unseen"]["baseline_connected_components"]
    assert 0.0 <= baseline[I.AP_MATCHED_75] <= 1.0 and baseline[I.COUNT_INSTANCES] > 0


def test_too_few_slots_are_refused_before_anything_is_written(tmp_path):
    done = gpnerf("run", "+head=instance", "+loss=instance", *TINY, "head.slots=2", "out_dir=few", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith("error: scene 'layout_00' frame 0 has 5 instance ids")
    assert "head.slots=2; set head.slots >= 5" in done.stderr and not (tmp_path / "few").exists()


def test_a_dataset_without_instance_ids_is_refused_before_training(tmp_path):
    from plugins.test_replica import write_frames

    root = tmp_path / "Replica"
    for scene in ("office_1", "office_0"):
        write_frames(root / scene / "Sequence_1", range(8), scene=1)
    model = [o for o in TINY if not o.startswith("dataset.")]
    done = gpnerf(
        "run", "+head=instance", "+loss=instance", *model, "dataset=replica", f"dataset.root={root}",
        "dataset.height=0", "dataset.width=0", "dataset.scenes=[office_1]", "dataset.unseen_scenes=[office_0]",
        "dataset.eval_start=2", "dataset.eval_step=4", "dataset.eval_count=1", "out_dir=none", cwd=tmp_path,
    )
    assert done.returncode != 0
    assert "dataset 'replica' has no instance ids (scene 'office_1/Sequence_1'" in done.stderr
    assert not (tmp_path / "none").exists()
