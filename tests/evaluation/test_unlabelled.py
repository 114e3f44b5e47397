"""Evaluation on scenes without labels: colour and depth are scored, every label metric is None with the reason (never
0), a split mixing labelled and unlabelled scenes scores labels on the labelled ones only, and says so."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.evaluation import instances as I
from gpnerf_core.evaluation import metrics as M
from gpnerf_core.evaluation.evaluator import ViewRecord, evaluate, print_summary, summarize
from gpnerf_core.evaluation.visualize import class_legend, label_palette
from gpnerf_core.data.frames import FrameCache
from pipeline_check import TINY_MODEL, TINY_SCENES
from unlabelled_scenes import UnlabelledScenes

K, IGNORE = 3, 255
EMBEDDED = dict(num_train_scenes=1, num_unseen_scenes=1, frames_per_scene=6, eval_every=3, height=32, width=48)


def record(position, scene, *, labelled=True, psnr=20.0, confusion=None, depth=None):
    """A view record as ``_evaluate_view`` makes it: label matrices only for a labelled scene."""
    matrix = confusion if labelled else None
    return ViewRecord(position=position, scene=scene, frame=position, quality={M.PSNR_CLAMPED: psnr,
                      M.SSIM_GAUSSIAN11: 0.5}, confusion=matrix, teacher_confusion=matrix,
                      baseline_confusion=matrix, seconds=0.1, rays=100, labelled=labelled, depth=depth)


GOOD = torch.tensor([[5, 1, 0], [0, 4, 0], [2, 0, 3]])
DEPTH = {M.DEPTH_ABS_REL: 0.1, M.DEPTH_RMSE: 0.2}


def test_a_split_without_labels_reports_every_label_metric_as_none_with_the_reason():
    records = [record(0, "capture", labelled=False, depth=DEPTH), record(1, "capture", labelled=False, psnr=22.0)]
    values = summarize(records, K, IGNORE, semantics=True, peak_memory=1.0)
    assert values[M.PSNR_CLAMPED] == pytest.approx(21.0) and values[M.SSIM_GAUSSIAN11] == pytest.approx(0.5)
    assert values[M.DEPTH_ABS_REL] == pytest.approx(0.1) and values[M.COUNT_IMAGES_WITH_DEPTH] == 1
    assert values[M.COUNT_IMAGES] == 2  # the images colour was scored on
    for key in (*M.SEGMENTATION_KEYS, "baseline_majority", "teacher_2d"):
        assert key in values and values[key] is None, key  # None, never 0.0
    assert values[M.LABELS_UNAVAILABLE_REASON] == "scene 'capture' has no labels"
    assert "per_scene" not in values and M.LABELS_UNLABELLED_SCENES not in values


def test_an_instance_head_without_labels_reports_its_aps_as_none():
    records = [record(0, "a", labelled=False), record(1, "b", labelled=False)]
    values = summarize(records, K, IGNORE, semantics=False, peak_memory=1.0, instance_head=True)
    assert all(values[key] is None for key in (*I.AP_KEYS, "teacher_2d"))
    assert values[M.LABELS_UNAVAILABLE_REASON] == "scenes 'a', 'b' have no labels"
    assert M.MIOU_IMAGE_MEAN_PRESENT not in values


def test_no_head_no_label_metrics_and_no_reason():
    # a colour-only model on a dataset without a class list: zero classes
    values = summarize([record(0, "capture", labelled=False)], 0, IGNORE, semantics=False, peak_memory=1.0)
    assert M.LABELS_UNAVAILABLE_REASON not in values and M.MIOU_IMAGE_MEAN_PRESENT not in values
    assert values[M.DEPTH_ABS_REL] is None and values[M.DEPTH_UNAVAILABLE_REASON]


def test_a_mixed_split_scores_labels_on_its_labelled_scenes_only_and_says_so():
    labelled = [record(0, "room", confusion=GOOD), record(1, "room", confusion=GOOD.T.contiguous())]
    mixed = [*labelled, record(2, "capture", labelled=False, psnr=10.0)]
    alone = summarize(labelled, K, IGNORE, semantics=True, peak_memory=1.0)
    values = summarize(mixed, K, IGNORE, semantics=True, peak_memory=1.0)
    for key in M.SEGMENTATION_KEYS:
        assert values[key] == alone[key], key
    assert values["baseline_majority"] == alone["baseline_majority"] and list(values["per_scene"]) == ["room"]
    assert values[M.LABELS_UNLABELLED_SCENES] == ["capture"] and values[M.COUNT_IMAGES_WITHOUT_LABELS] == 1
    assert values[M.PSNR_CLAMPED] == pytest.approx((20.0 + 10.0) / 2)  # colour on every scene, group then mean
    assert M.LABELS_UNAVAILABLE_REASON not in values


def test_the_summary_says_labels_are_not_available(capsys, tmp_path):
    unlabelled = summarize([record(0, "capture", labelled=False)], K, IGNORE, semantics=True, peak_memory=1.0)
    mixed = summarize([record(0, "room", confusion=GOOD), record(1, "capture", labelled=False)], K, IGNORE,
                      semantics=True, peak_memory=1.0)
    print_summary({"eval": {"train_heldout": mixed, "unseen": unlabelled}}, tmp_path)
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(" train_heldout: mIoU ") and "(labels scored on the labelled scenes only; without " \
                                                         "labels: capture)" in out[0]
    assert out[1] == ("        unseen: labels: not available (scene 'capture' has no labels) | PSNR 20.00 SSIM 0.500 "
                      "| 0.10 s/frame")


def test_depth_errors_use_cells_whose_every_pixel_has_depth():
    gt = torch.tensor([[2.0, 2.0, 4.0, 0.0], [2.0, 2.0, 4.0, 4.0]])
    pred = torch.tensor([[3.0, 1.0]])  # two 2x2 cells; the second has an unknown pixel
    errors = M.depth_errors(pred, gt)
    assert errors == {M.DEPTH_ABS_REL: pytest.approx(0.5), M.DEPTH_RMSE: pytest.approx(1.0)}
    assert M.depth_errors(pred, torch.zeros(2, 4)) is None
    with pytest.raises(ValueError, match="not a whole multiple"):
        M.depth_errors(pred, torch.ones(3, 4))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny untrained model (seeded) on the embedded rooms generated once into a folder."""
    root = tmp_path_factory.mktemp("rooms")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root}",
                   "eval.max_views_per_scene=1"])
    torch.manual_seed(0)
    return cfg, build_components(cfg), root


def _evaluate(tiny, run_dir, splits=("train", "unseen"), **options):
    cfg, components, root = tiny
    dataset = UnlabelledScenes(root=str(root), **{**EMBEDDED, **options})
    components = dataclasses.replace(components, dataset=dataset)
    cfg = cfg.copy()
    cfg.eval.splits = list(splits)
    return evaluate(cfg, components, FrameCache(dataset, torch.device("cpu")), run_dir, Distributed.single())


def test_evaluate_scores_colour_and_depth_and_no_label_on_scenes_without_labels(tiny, tmp_path, one_thread):
    metrics = _evaluate(tiny, tmp_path)
    assert metrics["baseline_class"] is None  # no training scene has labels to take a majority class from
    for split, scene in (("train_heldout", "layout_00"), ("unseen", "unseen_00")):
        values = metrics["eval"][split]
        for key in (M.PSNR_CLAMPED, M.SSIM_GAUSSIAN11, M.DEPTH_ABS_REL, M.DEPTH_RMSE):
            assert math.isfinite(values[key]), (split, key)
        assert values[M.MIOU_IMAGE_MEAN_PRESENT] is None and values[M.ACC_TOTAL] is None
        assert values["baseline_majority"] is None and values["teacher_2d"] is None
        assert values[M.LABELS_UNAVAILABLE_REASON] == f"scene {scene!r} has no labels"
    pictures = sorted(p.name for p in (tmp_path / "images" / "train_heldout").iterdir())
    assert pictures == ["layout_00_0001_depth.png", "layout_00_0001_features_pca.png", "layout_00_0001_rgb.png",
                        "layout_00_0001_semantic.png"]


def test_a_mixed_split_gives_the_labelled_scenes_numbers(tiny, tmp_path, one_thread):
    mixed = _evaluate(tiny, tmp_path / "mixed", ["train"], scenes=["layout_00", "unseen_00"],
                      without_labels=["unseen_00"])
    labelled = _evaluate(tiny, tmp_path / "labelled", ["train"], scenes=["layout_00"], without_labels=["unseen_00"])
    values, alone = mixed["eval"]["train_heldout"], labelled["eval"]["train_heldout"]
    assert values[M.LABELS_UNLABELLED_SCENES] == ["unseen_00"]
    for key in (*M.SEGMENTATION_KEYS, "baseline_majority", "teacher_2d"):
        assert values[key] == alone[key], key
    assert values[M.MIOU_IMAGE_MEAN_PRESENT] is not None


def test_the_class_legend_shows_each_class_in_its_label_colour():
    legend = class_legend(["wall", "floor", "a long class name"], swatch=12, gap=3)
    palette = label_palette(3)
    assert legend.dtype == np.uint8 and legend.shape[0] == 3 * (12 + 3) + 3
    for index in range(3):
        top = 3 + index * 15
        assert (legend[top:top + 12, 3:15] == palette[index]).all()
    assert legend.shape[1] > class_legend(["wall"]).shape[1]  # wide enough for the longest name
