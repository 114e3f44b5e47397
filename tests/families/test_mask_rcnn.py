"""Mask R-CNN (``model=mask_rcnn``, Table 2's 2D baseline): RoIAlign against a dense bilinear reference, NMS against a
brute-force one, the anchors, the Swin-T windows, a tiny training that lowers every loss term, AP 1 for perfect
masks, weights loaded from a file, a run scored on the real held-out image, and bad input refused in one line."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import pytest
import torch

from gpnerf_core.cli import main as cli_main
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.evaluation import instances as I
from gpnerf_core.testing.inputs import model_batch
from gpnerf_plugins.families.mask_rcnn.anchors import cell_anchors, grid_anchors, pyramid_anchors
from gpnerf_plugins.families.mask_rcnn.boxes import BoxCoder, box_iou, nms
from gpnerf_plugins.families.mask_rcnn.build import build_mask_rcnn
from gpnerf_plugins.families.mask_rcnn.detector import LOSS_NAMES
from gpnerf_plugins.families.mask_rcnn.roi_align import roi_align, roi_levels
from gpnerf_plugins.families.mask_rcnn.swin import SwinTransformer, shift_mask, window_partition, window_reverse
from gpnerf_plugins.families.mask_rcnn.targets import paste_masks, slot_logits, targets_from_ids
from pipeline_check import TINY_SCENES


class NoParts:
    def configured(self, kind: str) -> bool:
        return False


TINY = dict(anchor_sizes=[4.0, 8.0, 16.0, 24.0, 32.0], fpn_channels=8, box_hidden=16, mask_hidden=8,
            roi_batch_size_per_image=16, slots=8)


# ---- RoIAlign ---------------------------------------------------------------------------------------------------------

def reference_roi_align(features, rois, size, scale, ratio, aligned):
    """torchvision's CPU kernel written out sample by sample (python loops, float64)."""
    _, channels, height, width = features.shape
    out = []
    for roi in rois.tolist():
        b, x1, y1, x2, y2 = roi
        offset = 0.5 if aligned else 0.0
        sx, sy = x1 * scale - offset, y1 * scale - offset
        w, h = x2 * scale - offset - sx, y2 * scale - offset - sy
        if not aligned:
            w, h = max(w, 1.0), max(h, 1.0)
        bins = []
        for ph in range(size):
            row = []
            for pw in range(size):
                acc = features.new_zeros(channels)
                for iy in range(ratio):
                    y = sy + ph * h / size + (iy + 0.5) * h / size / ratio
                    for ix in range(ratio):
                        x = sx + pw * w / size + (ix + 0.5) * w / size / ratio
                        if y < -1.0 or y > height or x < -1.0 or x > width:
                            continue
                        yy, xx = max(y, 0.0), max(x, 0.0)
                        y0, x0 = int(yy), int(xx)
                        if y0 >= height - 1:
                            y0 = y1_ = height - 1
                            yy = float(y0)
                        else:
                            y1_ = y0 + 1
                        if x0 >= width - 1:
                            x0 = x1_ = width - 1
                            xx = float(x0)
                        else:
                            x1_ = x0 + 1
                        ly, lx = yy - y0, xx - x0
                        f = features[int(b)]
                        acc = acc + ((1 - ly) * (1 - lx) * f[:, y0, x0] + (1 - ly) * lx * f[:, y0, x1_]
                                     + ly * (1 - lx) * f[:, y1_, x0] + ly * lx * f[:, y1_, x1_])
                row.append(acc / (ratio * ratio))
            bins.append(torch.stack(row, dim=1))
        out.append(torch.stack(bins, dim=1))
    return torch.stack(out)


ROIS = torch.tensor([[0, 1.0, 1.5, 9.0, 6.0],      # inside
                     [1, -3.0, -2.0, 4.0, 3.0],    # over the top-left edge
                     [0, 10.0, 5.0, 14.0, 9.5],    # past the bottom-right edge
                     [1, 3.2, 2.1, 3.7, 2.4]],     # smaller than a cell
                    dtype=torch.float64)


@pytest.mark.parametrize("aligned", [True, False])
@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_roi_align_matches_the_dense_bilinear_reference_in_values_and_gradients(aligned, scale):
    g = torch.Generator().manual_seed(0)
    features = torch.randn(2, 3, 7, 11, generator=g, dtype=torch.float64, requires_grad=True)
    ours = roi_align(features, ROIS, 3, scale, 2, aligned)
    reference = reference_roi_align(features, ROIS, 3, scale, 2, aligned)
    assert ours.shape == (4, 3, 3, 3)
    assert torch.allclose(ours, reference, atol=1e-12)
    weights = torch.randn(ours.shape, generator=g, dtype=torch.float64)
    grad_ours, = torch.autograd.grad((ours * weights).sum(), features)
    grad_reference, = torch.autograd.grad((reference * weights).sum(), features)
    assert torch.allclose(grad_ours, grad_reference, atol=1e-12) and grad_ours.abs().sum() > 0


def test_roi_align_of_a_linear_ramp_is_the_bin_centres():
    ys, xs = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    ramp = (xs + 10 * ys)[None, None].double()
    out = roi_align(ramp, torch.tensor([[0, 1.0, 2.0, 5.0, 6.0]], dtype=torch.float64), 2, 1.0, 2, aligned=True)
    # aligned: the box spans continuous [1, 5] x [2, 6], i.e. cell coordinates [0.5, 4.5] x [1.5, 5.5]
    centres_x, centres_y = torch.tensor([1.5, 3.5]), torch.tensor([2.5, 4.5])
    assert torch.allclose(out[0, 0], (centres_x[None] + 10 * centres_y[:, None]).double())


def test_boxes_go_to_fpn_levels_by_their_size():
    boxes = torch.tensor([[0, 0, 8.0, 8.0], [0, 0, 112.0, 112.0], [0, 0, 224.0, 224.0], [0, 0, 2000.0, 2000.0]])
    assert roi_levels(boxes, 2, 5).tolist() == [2, 3, 4, 5]


# ---- NMS, boxes, anchors ----------------------------------------------------------------------------------------------

def brute_force_nms(boxes, scores, threshold):
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    kept = []
    for i in order:
        if all(box_iou(boxes[i:i + 1], boxes[j:j + 1])[0, 0] <= threshold for j in kept):
            kept.append(i)
    return kept


@pytest.mark.parametrize("seed", range(4))
def test_nms_keeps_what_a_brute_force_greedy_pass_keeps(seed):
    g = torch.Generator().manual_seed(seed)
    corners = torch.rand(60, 2, generator=g) * 50
    boxes = torch.cat([corners, corners + 5 + torch.rand(60, 2, generator=g) * 20], dim=1)
    scores = torch.rand(60, generator=g).round(decimals=1)  # ties too
    for threshold in (0.3, 0.5, 0.7):
        assert nms(boxes, scores, threshold).tolist() == brute_force_nms(boxes, scores, threshold)


def test_the_box_coder_round_trips():
    coder = BoxCoder((10.0, 10.0, 5.0, 5.0))
    references = torch.tensor([[2.0, 3.0, 10.0, 7.0], [0.0, 0.0, 50.0, 20.0]])
    boxes = torch.tensor([[1.0, 4.0, 12.0, 9.0], [5.0, 2.0, 40.0, 30.0]])
    assert torch.allclose(coder.decode(coder.encode(boxes, references), references), boxes, atol=1e-5)


def test_anchors_are_torchvisions():
    assert cell_anchors(32.0, [0.5, 1.0, 2.0]).tolist() == [[-23.0, -11.0, 23.0, 11.0], [-16.0, -16.0, 16.0, 16.0],
                                                            [-11.0, -23.0, 11.0, 23.0]]
    anchors = grid_anchors(8.0, [1.0], (2, 3), (4, 4))
    assert anchors.tolist() == [[-4.0, -4.0, 4.0, 4.0], [0.0, -4.0, 8.0, 4.0], [4.0, -4.0, 12.0, 4.0],
                                [-4.0, 0.0, 4.0, 8.0], [0.0, 0.0, 8.0, 8.0], [4.0, 0.0, 12.0, 8.0]]
    levels = pyramid_anchors([8.0, 16.0, 32.0, 64.0, 128.0], [0.5, 1.0, 2.0], [(24, 32), (12, 16), (6, 8), (3, 4), (2, 2)],
                             (96, 128))
    assert [len(a) for a in levels] == [24 * 32 * 3, 12 * 16 * 3, 6 * 8 * 3, 3 * 4 * 3, 2 * 2 * 3]
    sides = [float((a[:, 2] - a[:, 0]).mul(a[:, 3] - a[:, 1]).sqrt().mean()) for a in levels]
    assert sides == pytest.approx([8, 16, 32, 64, 128], rel=0.05)  # corners rounded to pixels
    assert levels[4][3 * 3 + 1].tolist() == [64 - 64.0, 48 - 64.0, 64 + 64.0, 48 + 64.0]  # P6 is 48 px high, 64 wide


# ---- Swin-T -----------------------------------------------------------------------------------------------------------

def test_swin_t_pads_its_windows_and_gives_four_levels():
    x = torch.randn(1, 5 * 7, 2 * 7 + 3, 6)
    padded = torch.nn.functional.pad(x, (0, 0, 0, 4))  # [1, 35, 21, 6]
    assert torch.equal(window_reverse(window_partition(padded, 7), 7, 35, 21), padded)
    mask = shift_mask(28, 35, 7, 3, torch.device("cpu"))
    assert mask.shape == (20, 49, 49) and mask[0].abs().sum() == 0 and (mask[-1] == -100).any()
    swin = SwinTransformer(drop_path=0.0).eval()
    levels = swin(torch.rand(1, 3, 96, 128))
    assert [tuple(level.shape[1:]) for level in levels] == [(96, 24, 32), (192, 12, 16), (384, 6, 8), (768, 3, 4)]
    assert swin.stages[2][1].shift == 3 and len(swin.stages[2]) == 6 and swin.stages[3][0].attn.heads == 24


# ---- training and scoring ---------------------------------------------------------------------------------------------

def two_objects() -> tuple[torch.Tensor, torch.Tensor]:
    """A 32 x 48 image ``[3, H, W]`` of two flat-coloured rectangles on grey, and its ids ``[H, W]`` (0 = background)."""
    ids = torch.zeros(32, 48, dtype=torch.int64)
    ids[4:14, 5:20] = 3
    ids[18:30, 26:44] = 5
    image = torch.full((3, 32, 48), 0.5)
    image[:, ids == 3] = torch.tensor([0.9, 0.2, 0.1])[:, None]
    image[:, ids == 5] = torch.tensor([0.1, 0.3, 0.9])[:, None]
    return image, ids


def test_targets_are_tight_boxes_of_every_id_background_included():
    _, ids = two_objects()
    targets = targets_from_ids(ids)
    assert targets.boxes.tolist() == [[0.0, 0.0, 48.0, 32.0], [5.0, 4.0, 20.0, 14.0], [26.0, 18.0, 44.0, 30.0]]
    assert targets.labels.tolist() == [1, 1, 1] and targets.masks.sum().item() == 32 * 48


def test_a_tiny_training_lowers_every_loss_term():
    torch.manual_seed(0)
    family = build_mask_rcnn(parts=NoParts(), **TINY)
    image, ids = two_objects()
    targets = [targets_from_ids(ids)]
    optimizer = torch.optim.Adam(family.parameters(), lr=1e-3)

    def losses():
        return family.detector.losses(image[None], targets, torch.Generator().manual_seed(0))

    before = {k: v.item() for k, v in losses().items()}
    for step in range(10):
        terms = family.detector.losses(image[None], targets, torch.Generator().manual_seed(step))
        optimizer.zero_grad()
        sum(terms.values()).backward()
        optimizer.step()
    after = {k: v.item() for k, v in losses().items()}
    assert set(before) == set(LOSS_NAMES)
    assert all(after[name] < before[name] for name in LOSS_NAMES), (before, after)


def test_ap_of_perfect_masks_is_one_through_crop_paste_and_slot_scores():
    _, ids = two_objects()
    targets = targets_from_ids(ids)
    crops = roi_align(targets.masks[:, None], torch.cat([torch.arange(3.0)[:, None], targets.boxes], 1), 28, 1.0, 2,
                      True)[:, 0]
    pasted = paste_masks(crops, targets.boxes, *ids.shape)
    logits = slot_logits(pasted, torch.tensor([0.9, 0.8, 0.7]), slots=8)
    assert logits.shape == (1, 9, 32, 48)
    slots, confidence = I.slot_predictions(logits[0], "sigmoid")
    record, _ = I.instance_record(slots, confidence, ids)
    accumulator = I.InstanceAccumulator()
    accumulator.add(record, group="scene")
    scores = accumulator.compute()
    assert scores[I.AP_MATCHED_75] == pytest.approx(1.0) and scores["instance/coco_mask_ap"] == pytest.approx(1.0)


def test_weights_saved_to_a_file_load_into_a_fresh_model_with_the_same_detections(tmp_path):
    torch.manual_seed(1)
    first = build_mask_rcnn(parts=NoParts(), **TINY).eval()
    torch.save(first.state_dict(), tmp_path / "weights.pt")
    torch.manual_seed(2)
    second = build_mask_rcnn(parts=NoParts(), **TINY).eval()
    image = two_objects()[0][None]
    assert not torch.equal(first.detector.detect(image)[0].scores, second.detector.detect(image)[0].scores)
    second.load_state_dict(torch.load(tmp_path / "weights.pt", weights_only=True), strict=True)
    a, b = first.detector.detect(image)[0], second.detector.detect(image)[0]
    assert torch.equal(a.boxes, b.boxes) and torch.equal(a.masks, b.masks)


def test_torchvisions_checkpoint_from_a_local_file_loads_key_for_key(tmp_path):
    """torchvision's names (v2 wrappers for the FPN and RPN convs, v1's ``mask_fcn<k>`` for the mask head: both
    occur) written by the test; ``model.init`` maps them onto the family, and the detections follow the weights."""
    from gpnerf_core.model.weights import init_weights
    from gpnerf_plugins.families.mask_rcnn.torchvision_keys import candidates

    options = dict(backbone="resnet50", classes=3, fpn_channels=8, box_hidden=16, mask_hidden=8,
                   anchor_sizes=[4.0, 8.0, 16.0, 24.0, 32.0], aligned=False)
    torch.manual_seed(3)
    source = build_mask_rcnn(parts=NoParts(), **options).eval()
    assert sum(p.numel() for p in build_mask_rcnn(  # torchvision's maskrcnn_resnet50_fpn has 44,401,393
        parts=NoParts(), backbone="resnet50", classes=90, fpn_channels=256, box_hidden=1024, mask_hidden=256).parameters()
               ) == 44_401_393
    written = {}
    for key, value in source.state_dict().items():
        names = candidates(key)
        assert names, key
        written[names[-1] if ".mask_head.convs." in key else names[0]] = value.clone()
    assert "roi_heads.mask_head.mask_fcn1.weight" in written and "rpn.head.conv.0.0.weight" in written
    torch.save(written, tmp_path / "maskrcnn_resnet50_fpn.pth")
    torch.manual_seed(4)
    target = build_mask_rcnn(parts=NoParts(), **options).eval()
    report = init_weights(target, tmp_path / "maskrcnn_resnet50_fpn.pth")
    assert report.fmt == "torchvision_maskrcnn" and not report.missing and not report.unexpected
    image = two_objects()[0][None]
    for name, tensor in source.state_dict().items():
        assert torch.equal(tensor, target.state_dict()[name]), name
    a, b = source.detector.detect(image)[0], target.detector.detect(image)[0]
    assert torch.equal(a.scores, b.scores) and torch.equal(a.masks, b.masks)


def test_torchvisions_resizing_scales_the_detections_back_to_the_frame():
    torch.manual_seed(5)
    family = build_mask_rcnn(parts=NoParts(), **{**TINY, "min_size": 64, "score_threshold": 0.0}).eval()
    resized, ratios = family.detector._resized(two_objects()[0][None])
    assert tuple(resized.shape[-2:]) == (64, 96) and ratios == (2.0, 2.0)
    with torch.no_grad():
        found = family.detector.detect(two_objects()[0][None])[0]
    assert len(found.boxes) and float(found.boxes[:, 2].max()) <= 48.0 and float(found.boxes[:, 3].max()) <= 32.0


# ---- bad input --------------------------------------------------------------------------------------------------------

def test_anchors_larger_than_the_image_are_refused_naming_the_key():
    family = build_mask_rcnn(parts=NoParts(), **TINY)
    family.check_image_size(32, 48)
    with pytest.raises(ConfigError, match=r"model.anchor_sizes=\[4.0, 8.0, 16.0, 24.0, 32.0\]: an anchor of 32 px is "
                                          r"larger than the 24 x 30 images"):
        family.check_image_size(24, 30)
    with pytest.raises(ConfigError, match=r"model.anchor_sizes=.*expected 5 sizes"):
        build_mask_rcnn(parts=NoParts(), anchor_sizes=[8.0, 16.0])


def test_frames_without_instance_ids_are_refused_in_training():
    family = build_mask_rcnn(parts=NoParts(), **TINY).train()
    batch = model_batch(sources=False, whole_images=True, views=1)
    view = batch.views[0]
    with pytest.raises(DataError, match=r"scene 'kit' frame 0: no instance ids to train model=mask_rcnn on"):
        family(type(batch)((replace(view, instances=None),)), semantics=False)


def test_more_instances_than_detections_is_said_once_naming_the_key(caplog):
    family = build_mask_rcnn(parts=NoParts(), **{**TINY, "slots": 2}).train()
    batch = model_batch(sources=False, whole_images=True, views=2)  # 3 ids in every frame
    with caplog.at_level(logging.WARNING):
        family(batch, semantics=False)
        family(batch, semantics=False)
    said = [r.getMessage() for r in caplog.records if "model.slots" in r.getMessage()]
    assert len(said) == 1 and "has 3 instance ids (background included), more than model.slots=2" in said[0]


def test_predict_without_a_real_image_is_refused():
    from gpnerf_core.testing.inputs import model_view

    camera, _ = model_view(sources=False)
    with pytest.raises(ConfigError, match="segments a real image"):
        build_mask_rcnn(parts=NoParts(), **TINY).predict(camera, None, stride=1, chunk_rays=0)


# ---- through the commands ---------------------------------------------------------------------------------------------

RUN = ["dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
       "dataset.num_train_scenes=1", "dataset.scenes=[layout_00]", "model.anchor_sizes=[4,8,16,24,32]",
       "model.fpn_channels=8", "model.box_hidden=16", "model.mask_hidden=8", "model.roi_batch_size_per_image=16",
       "train.steps=2", "train.warmup_steps=0", "threads=1", "eval.save_images=0"]


def test_a_run_scores_the_real_held_out_image_and_eval_and_report_read_it(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli_main(["run", "+experiment=baselines/mask_rcnn", *RUN, f"out_dir={out}"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    scores = metrics["eval"]["train_heldout"]
    assert 0.0 <= scores["instance/ap_matched@0.75"] <= 1.0 and 0.0 <= scores["instance/coco_mask_ap"] <= 1.0
    assert scores["psnr/clamped"] is None and scores["depth/abs_rel"] is None  # a 2D model renders nothing to score
    assert {f"train/{name}" for name in LOSS_NAMES} <= {line.split(",")[1] for line in
                                                        (out / "scalars.csv").read_text().splitlines()[1:]}
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    assert cli_main(["eval", f"checkpoint={checkpoint}", f"out_dir={tmp_path / 'again'}"]) == 0
    again = json.loads((tmp_path / "again" / "metrics.json").read_text())["eval"]["train_heldout"]
    assert again["instance/ap_matched@0.75"] == scores["instance/ap_matched@0.75"]
    capsys.readouterr()
    assert cli_main(["report", str(out), "--chart", str(tmp_path / "chart")]) == 0
    assert "| mask_rcnn |" in capsys.readouterr().out
    assert "Mask R-CNN (2D)" in (tmp_path / "chart" / "speed_accuracy.csv").read_text()
    with pytest.raises(SystemExit) as refused:  # a 2D model renders no trajectory
        cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"])
    assert refused.value.code == 2 and "render renders novel views, and model=mask_rcnn is a 2D model" in capsys.readouterr().err


def test_the_swin_t_experiment_builds_swin_t():
    from gpnerf_core.config.compose import compose
    from gpnerf_core.model.build import build_components

    cfg = compose(["+experiment=baselines/mask_rcnn_swin_t", *TINY_SCENES, "dataset.scenes=[layout_00]",
                   "model.anchor_sizes=[4,8,16,24,32]"])
    model = build_components(cfg).model
    assert type(model.detector.backbone.body).__name__ == "SwinTransformer" and cfg.get("loss") is None


def test_a_dataset_without_instance_ids_is_refused_naming_it():
    from gpnerf_core.config.compose import compose
    from gpnerf_core.engine.validation import check_data
    from gpnerf_core.model.build import build_components

    cfg = compose(["+experiment=baselines/mask_rcnn", *TINY_SCENES, "dataset.scenes=[layout_00]",
                   "model.anchor_sizes=[4,8,16,24,32]"])
    components = build_components(cfg)
    first = components.dataset.load_scene("layout_00")
    stripped = replace(first, load_frame=lambda i: replace(first.load_frame(i), instance=None))
    components.dataset.load_scene = lambda name: stripped
    with pytest.raises(ConfigError, match=r"dataset 'embedded' has no instance ids \(scene 'layout_00', frame \d+\), "
                                          r"but model 'mask_rcnn' predicts instances; use a dataset with instance ids"):
        check_data(cfg, components, training=True)
