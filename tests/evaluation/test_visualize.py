"""Pictures: exact colours, determinism, shapes and atomic saving."""

from __future__ import annotations

import os

import matplotlib
import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.evaluation import visualize as vis

IGNORE = 255


def test_palette_is_deterministic_distinct_and_not_black():
    palette = vis.label_palette(300)
    assert palette.dtype == np.uint8 and palette.shape == (300, 3)
    assert np.array_equal(palette, vis.label_palette(300))
    assert len({tuple(row) for row in palette}) == 300
    assert not (palette == 0).all(axis=1).any()
    # Stable prefix: a class keeps its colour whatever the class count.
    assert np.array_equal(vis.label_palette(21), palette[:21])
    assert palette[:3].tolist() == [[128, 0, 0], [0, 128, 0], [128, 128, 0]]


def test_colorize_labels_uses_palette_and_draws_ignore_black():
    labels = torch.tensor([[0, 1], [2, IGNORE]])
    image = vis.colorize_labels(labels, 3, IGNORE)
    palette = vis.label_palette(3)
    assert image.dtype == np.uint8 and image.shape == (2, 2, 3)
    assert image[0, 0].tolist() == palette[0].tolist()
    assert image[1, 0].tolist() == palette[2].tolist()
    assert image[1, 1].tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="label 5"):
        vis.colorize_labels(torch.tensor([[5]]), 3, IGNORE)


def test_error_map_three_colours():
    gt = np.array([[0, 1, IGNORE]])
    pred = np.array([[0, 0, 1]])
    image = vis.error_map(pred, gt, IGNORE)
    assert [tuple(px) for px in image[0]] == [vis.CORRECT_COLOUR, vis.WRONG_COLOUR, vis.IGNORED_COLOUR]


def test_rgb_error_map_scale():
    gt = np.full((2, 3, 3), 0.5)
    pred = gt.copy()
    pred[0, 0] = 1.0  # error 0.5 > max_error: saturates
    pred[0, 1] = 0.5 + 0.125  # half the scale
    image = vis.rgb_error_map(pred, gt, max_error=0.25)
    cmap = matplotlib.colormaps["inferno"]
    expected = lambda v: np.round(np.asarray(cmap(v)[:3]) * 255).astype(np.uint8).tolist()  # noqa: E731
    assert image[0, 0].tolist() == expected(1.0)
    assert image[0, 1].tolist() == expected(0.5)
    assert image[1, 2].tolist() == expected(0.0)


def test_depth_to_color_range_and_unknown():
    depth = torch.tensor([[1.0, 3.0, 0.0, 2.0]])
    image = vis.depth_to_color(depth, near=1.0, far=3.0)
    cmap = matplotlib.colormaps["turbo"]
    assert image[0, 0].tolist() == np.round(np.asarray(cmap(0.0)[:3]) * 255).astype(np.uint8).tolist()
    assert image[0, 1].tolist() == np.round(np.asarray(cmap(1.0)[:3]) * 255).astype(np.uint8).tolist()
    assert image[0, 2].tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="far > near"):
        vis.depth_to_color(depth, 2.0, 2.0)


def test_pca_rgb_shape_and_determinism():
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(8, 5, 6, generator=generator)
    image = vis.pca_rgb(features)
    assert image.dtype == np.uint8 and image.shape == (5, 6, 3)
    assert np.array_equal(image, vis.pca_rgb(features.clone()))
    assert np.array_equal(image, vis.pca_rgb(features.numpy()))
    for channel in range(3):  # each channel min-max normalised
        assert image[..., channel].min() == 0 and image[..., channel].max() == 255


@pytest.mark.parametrize("lead_sign", [1.0, -1.0])
def test_pca_rgb_sign_convention(lead_sign):
    # Features vary along one direction d; the first component is +-d / |d| with its largest loading positive, so
    # the first channel rises with the ramp when d's largest entry is positive and falls otherwise.
    ramp = torch.linspace(0.0, 1.0, 12).reshape(3, 4)
    direction = torch.tensor([3.0, -1.0, 0.5, 0.0]) * lead_sign
    features = direction[:, None, None] * ramp[None]
    image = vis.pca_rgb(features)
    first = image[..., 0].reshape(-1).astype(int)
    steps = np.diff(first)
    if lead_sign > 0:
        assert (steps >= 0).all() and first[0] == 0 and first[-1] == 255
    else:
        assert (steps <= 0).all() and first[0] == 255 and first[-1] == 0


def test_pca_rgb_few_channels_and_bad_input():
    features = torch.arange(6.0).reshape(1, 2, 3)
    image = vis.pca_rgb(features)
    assert image[..., 0].reshape(-1).tolist() == [0, 51, 102, 153, 204, 255]
    assert (image[..., 1:] == 0).all()
    with pytest.raises(ValueError, match="NaN"):
        vis.pca_rgb(torch.full((3, 2, 2), float("nan")))


def test_side_by_side_layout():
    a = np.full((4, 5, 3), 10, np.uint8)
    b = np.full((6, 3), 200, np.uint8)
    panel = vis.side_by_side([a, b], ["rgb", "gt"], gap=4, title_height=16)
    assert panel.dtype == np.uint8 and panel.shape == (16 + 6, 5 + 4 + 3, 3)
    assert (panel[16:20, 0:5] == 10).all()
    assert (panel[16:22, 9:12] == 200).all()
    assert (panel[:, 5:9] == 255).all()  # white gap
    assert (panel[:16] < 255).any()  # a title was drawn
    bare = vis.side_by_side([a, b])
    assert bare.shape == (6, 12, 3)
    with pytest.raises(ValueError, match="labels"):
        vis.side_by_side([a], ["x", "y"])
    with pytest.raises(ValueError, match="uint8"):
        vis.side_by_side([a.astype(np.float32)])


def test_save_image_round_trip(tmp_path):
    image = vis.colorize_labels(np.array([[0, 1], [2, IGNORE]]), 3, IGNORE)
    path = vis.save_image(tmp_path / "renders" / "sem.png", image)
    assert np.array_equal(np.asarray(Image.open(path)), image)
    assert os.listdir(path.parent) == ["sem.png"]


def test_plot_training_curves(tmp_path):
    history = [
        {"step": i, "seconds": 0.5 * i, "loss/total": 1.0 / (i + 1), "loss/rgb": 0.5 / (i + 1), "note": "x"}
        | ({"psnr/clamped": 20.0 + i, "miou/dataset": 0.1 * i} if i % 3 == 0 else {})
        for i in range(10)
    ]
    path = vis.plot_training_curves(history, tmp_path / "curves.png")
    with Image.open(path) as chart:
        width, height = chart.size
    # Two columns (step, wall clock) and three rows (loss, miou, psnr) at 100 dpi.
    assert (width, height) == (1200, 900)
    assert os.listdir(tmp_path) == ["curves.png"]
    step_only = vis.plot_training_curves([{"step": 0, "loss": 1.0}, {"step": 1, "loss": 0.5}], tmp_path / "s.png")
    with Image.open(step_only) as chart:
        assert chart.size == (600, 300)


def test_plot_training_curves_explicit_loss_keys(tmp_path):
    history = [{"step": i, "seconds": float(i), "rgb": 0.1, "ce": 2.0, "loss": 2.1, "lr": 1e-3} for i in range(3)]
    path = vis.plot_training_curves(history, tmp_path / "c.png", loss_keys=["rgb", "ce", "loss"])
    with Image.open(path) as chart:
        assert chart.size == (1200, 600)  # rows: the three losses together, then lr
    path = vis.plot_training_curves(history, tmp_path / "d.png")
    with Image.open(path) as chart:
        assert chart.size == (1200, 1200)  # without loss_keys: rows loss, ce, lr, rgb


def test_plot_training_curves_bad_history(tmp_path):
    with pytest.raises(ValueError, match="entry 1"):
        vis.plot_training_curves([{"step": 0, "loss": 1.0}, {"loss": 2.0}], tmp_path / "c.png")
    with pytest.raises(ValueError, match="no numeric series"):
        vis.plot_training_curves([{"step": 0, "seconds": 1.0}], tmp_path / "c.png")
    assert os.listdir(tmp_path) == []


def test_pca_rgb_is_invariant_to_channel_order():
    # Permuting channels permutes the loadings; eigh may then return either sign, the convention must undo it.
    generator = torch.Generator().manual_seed(1)
    mixing = torch.randn(6, 6, generator=generator) * torch.tensor([4.0, 3.0, 2.0, 0.5, 0.2, 0.1])
    features = torch.einsum("ck,khw->chw", mixing, torch.randn(6, 7, 9, generator=generator))
    image = vis.pca_rgb(features)
    for seed in range(6):
        order = torch.randperm(6, generator=torch.Generator().manual_seed(seed))
        # <= 1 grey level: float rounding of a permuted sum may move a pixel across a .5 boundary.
        assert np.abs(vis.pca_rgb(features[order]).astype(int) - image).max() <= 1
