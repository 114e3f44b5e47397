"""Tests of the loss terms and the rgb/ce/sd/dgs/label_free loss sets."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from gpnerf_core.errors import ConfigError
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_core.types import LossInputs, RaySamples, RenderedRays
from gpnerf_plugins.losses.sets import (
    CeLossConfig,
    DgsLossConfig,
    LabelFreeLossConfig,
    LabelFreeLossSet,
    LossSetConfig,
    RgbLossConfig,
    SdLossConfig,
    WeightedLossSet,
)
from gpnerf_plugins.losses.terms import (
    centre_from_depth,
    cosine_distance,
    cross_entropy,
    depth_guided_distance,
    rgb_mse,
    sample_window,
)

IGNORE = 7
RGB_ONLY = dict(ce_weight=0.0, sd_weight=0.0, dgs_weight=0.0)


def _rays(num_rays: int, num_samples: int, channels: int, *, semantic: bool = True) -> RenderedRays:
    depths = torch.linspace(1.0, 4.0, num_samples).expand(num_rays, num_samples).contiguous()
    weights = torch.softmax(torch.randn(num_rays, num_samples), dim=-1)
    return RenderedRays(
        rgb=torch.rand(num_rays, 3, requires_grad=True),
        weights=weights,
        depth=(weights * depths).sum(-1),
        samples=RaySamples(depths=depths, points=torch.zeros(num_rays, num_samples, 3)),
        semantic=torch.randn(num_rays, channels, requires_grad=True) if semantic else None,
        sample_semantic=torch.randn(num_rays, num_samples, channels, requires_grad=True) if semantic else None,
    )


def _inputs(num_rays=6, num_samples=8, channels=5, *, fine=True, classes=4, size=(5, 6), **overrides) -> LossInputs:
    torch.manual_seed(0)
    fields = dict(
        coarse=_rays(num_rays, num_samples, channels, semantic=not fine),
        fine=_rays(num_rays, num_samples + 2, channels) if fine else None,
        target_rgb=torch.rand(num_rays, 3),
        target_depth=torch.rand(num_rays) * 3 + 1,
        logits=torch.randn(1, classes, *size, requires_grad=True),
        labels=torch.randint(0, classes, (1, *size)),
        teacher_at_rays=torch.randn(num_rays, channels, requires_grad=True),
        ignore_index=IGNORE,
    )
    fields.update(overrides)
    return LossInputs(**fields)


# ----------------------------------------------------------------------------------------------- terms


def test_rgb_mse_is_the_per_channel_mean():
    pred = torch.tensor([[0.0, 0.5, 1.0], [1.0, 1.0, 1.0]])
    target = torch.zeros(2, 3)
    assert rgb_mse(pred, target).item() == pytest.approx((0 + 0.25 + 1 + 3) / 6)


def test_cross_entropy_matches_torch_on_valid_pixels():
    torch.manual_seed(0)
    logits = torch.randn(1, 4, 3, 5)
    labels = torch.randint(0, 4, (1, 3, 5))
    labels[0, 0] = IGNORE
    expected = F.cross_entropy(logits, labels, ignore_index=IGNORE)
    torch.testing.assert_close(cross_entropy(logits, labels, IGNORE), expected)


def test_cross_entropy_of_an_all_ignored_image_is_zero_and_finite():
    logits = torch.randn(1, 3, 4, 4, requires_grad=True)
    loss = cross_entropy(logits, torch.full((1, 4, 4), IGNORE), IGNORE)
    assert loss.item() == 0.0 and torch.isfinite(loss)
    loss.backward()
    assert torch.isfinite(logits.grad).all() and logits.grad.abs().sum() == 0


@pytest.mark.parametrize("bad", [3, -1])
def test_cross_entropy_rejects_labels_outside_the_head(bad):
    labels = torch.zeros(1, 2, 2, dtype=torch.long)
    labels[0, 1, 1] = bad
    with pytest.raises(ConfigError, match=f"label {bad} .* 3 classes"):
        cross_entropy(torch.randn(1, 3, 2, 2), labels, IGNORE)


def test_cross_entropy_rejects_mismatched_sizes():
    with pytest.raises(ConfigError, match="same size"):
        cross_entropy(torch.randn(1, 3, 4, 4), torch.zeros(1, 4, 5, dtype=torch.long), IGNORE)


def test_cosine_distance_by_hand():
    student = torch.tensor([[1.0, 0.0], [0.0, 2.0], [-3.0, 0.0]])
    teacher = torch.tensor([[2.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    assert cosine_distance(student, teacher).item() == pytest.approx((0.0 + 1.0 + 2.0) / 3)


@pytest.mark.parametrize(
    "centre, expected",
    [(0, [0, 1, 2, 3, 4]), (1, [0, 1, 2, 3, 4]), (2, [0, 1, 2, 3, 4]), (5, [3, 4, 5, 6, 7]),
     (8, [5, 6, 7, 8, 9]), (9, [5, 6, 7, 8, 9])],
)
def test_window_is_shifted_into_range_never_wrapped(centre, expected):
    window = sample_window(torch.tensor([centre]), num_samples=10, half_width=2)
    assert window.tolist() == [expected]


def test_window_for_every_centre_is_full_width_and_in_range():
    num_samples = 64
    window = sample_window(torch.arange(num_samples), num_samples, half_width=2)
    assert window.shape == (num_samples, 5)
    assert window.min() == 0 and window.max() == num_samples - 1
    assert (window.diff(dim=1) == 1).all()
    assert (window == torch.arange(num_samples)[:, None]).any(dim=1).all()  # the centre is always inside


def test_window_wider_than_the_ray_covers_every_sample():
    assert sample_window(torch.tensor([0, 2]), num_samples=3, half_width=2).tolist() == [[0, 1, 2], [0, 1, 2]]
    assert sample_window(torch.tensor([4]), num_samples=7, half_width=0).tolist() == [[4]]


def _hand_example():
    # cos with the teacher (1, 0): 1, 0, -1, 1/sqrt(2)
    features = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [1.0, 1.0]]])
    return features, torch.tensor([[1.0, 0.0]])


@pytest.mark.parametrize(
    "centre, push, expected",
    [
        (0, False, (0.0 + 1.0 + 2.0) / 3),
        (0, True, (0.0 + 1.0 + 2.0) / 3 + 1 / math.sqrt(2)),
        (3, False, (1.0 + 2.0 + 1 - 1 / math.sqrt(2)) / 3),
        (3, True, (1.0 + 2.0 + 1 - 1 / math.sqrt(2)) / 3 + 1.0),
        (2, True, (1.0 + 2.0 + 1 - 1 / math.sqrt(2)) / 3 + 1.0),
        (1, True, (0.0 + 1.0 + 2.0) / 3 + 1 / math.sqrt(2)),
    ],
)
def test_depth_guided_distance_by_hand(centre, push, expected):
    features, teacher = _hand_example()
    window = sample_window(torch.tensor([centre]), num_samples=4, half_width=1)
    assert depth_guided_distance(features, teacher, window, push).item() == pytest.approx(expected, abs=1e-6)


def test_push_away_ignores_samples_already_pointing_away():
    features, teacher = _hand_example()
    window = sample_window(torch.tensor([3]), num_samples=4, half_width=0)  # outside: cos 1, 0, -1
    pull = 1 - 1 / math.sqrt(2)
    assert depth_guided_distance(features, teacher, window, True).item() == pytest.approx(pull + 1.0 / 3, abs=1e-6)


def test_gt_depth_centre_picks_the_nearest_sample_and_falls_back_when_unknown():
    depths = torch.tensor([[1.0, 2.0, 3.0, 4.0]] * 3)
    weights = torch.tensor([[0.1, 0.2, 0.3, 0.4]] * 3)
    centre = centre_from_depth(depths, torch.tensor([2.2, 0.0, 3.6]), weights)
    assert centre.tolist() == [1, 3, 3]
    centre = centre_from_depth(depths, torch.tensor([0.9, 100.0, 2.6]), weights)
    assert centre.tolist() == [0, 3, 2]


# -------------------------------------------------------------------------------------------- the sets


@pytest.mark.parametrize(
    "config, keys, semantics, sample_semantics, labels",
    [
        (RgbLossConfig, {"rgb"}, False, False, False),
        (CeLossConfig, {"rgb", "ce"}, True, False, True),
        (SdLossConfig, {"rgb", "ce", "sd"}, True, False, True),
        (DgsLossConfig, {"rgb", "ce", "sd", "dgs"}, True, True, True),
        (LabelFreeLossConfig, {"rgb", "sd", "dgs"}, True, True, False),
    ],
)
def test_registered_sets_return_their_terms_and_flags(config, keys, semantics, sample_semantics, labels):
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.losses.plugin",), autoload=False))
    assert registry.names("loss") == ["ce", "dgs", "dm_nerf", "image", "instance", "label_free", "rgb", "sd"]
    loss_set = registry.build("loss", OmegaConf.structured(config))
    assert (loss_set.needs_semantics, loss_set.needs_sample_semantics) == (semantics, sample_semantics)
    assert loss_set.needs_labels is labels
    terms = loss_set(_inputs())
    assert set(terms) == keys
    assert all(t.dim() == 0 and torch.isfinite(t) for t in terms.values())


def test_terms_are_weighted_and_rgb_sums_both_passes():
    inputs = _inputs()
    weights = dict(rgb_weight=0.5, ce_weight=2.0, sd_weight=0.3, dgs_weight=0.7)
    terms = WeightedLossSet(**weights, dgs_window=1)(inputs)
    last = inputs.fine
    rgb = rgb_mse(inputs.coarse.rgb, inputs.target_rgb) + rgb_mse(last.rgb, inputs.target_rgb)
    torch.testing.assert_close(terms["rgb"], 0.5 * rgb)
    torch.testing.assert_close(terms["ce"], 2.0 * cross_entropy(inputs.logits, inputs.labels, IGNORE))
    torch.testing.assert_close(terms["sd"], 0.3 * cosine_distance(last.semantic, inputs.teacher_at_rays))
    window = sample_window(last.weights.argmax(-1), last.weights.shape[1], 1)
    dgs = depth_guided_distance(last.sample_semantic, inputs.teacher_at_rays, window, False)
    torch.testing.assert_close(terms["dgs"], 0.7 * dgs)


def test_without_fine_pass_the_coarse_pass_carries_everything():
    inputs = _inputs(fine=False)
    terms = WeightedLossSet()(inputs)
    torch.testing.assert_close(terms["rgb"], rgb_mse(inputs.coarse.rgb, inputs.target_rgb))
    torch.testing.assert_close(terms["sd"], 0.25 * cosine_distance(inputs.coarse.semantic, inputs.teacher_at_rays))


def test_gt_depth_centre_through_the_set():
    inputs = _inputs(num_rays=2, num_samples=4, channels=2, fine=False)
    depths = inputs.coarse.samples.depths  # 1, 2, 3, 4 on both rays
    features = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [1.0, 1.0]]] * 2)
    teacher = torch.tensor([[1.0, 0.0]] * 2)
    weights = torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 2)
    coarse = RenderedRays(
        rgb=inputs.coarse.rgb, weights=weights, depth=(weights * depths).sum(-1), samples=inputs.coarse.samples,
        semantic=torch.randn(2, 2), sample_semantic=features,
    )
    inputs = _inputs(
        num_rays=2, num_samples=4, channels=2, fine=False, coarse=coarse, teacher_at_rays=teacher,
        target_depth=torch.tensor([1.1, 0.0]),
    )
    dgs_only = dict(rgb_weight=0.0, ce_weight=0.0, sd_weight=0.0, dgs_weight=1.0, dgs_window=0)
    loss_set = WeightedLossSet(**dgs_only, dgs_center="gt_depth")
    # Ray 0: nearest sample to 1.1 m is index 0 (cos 1 -> 0); ray 1 has no depth: argmax weight index 3.
    expected = (0.0 + (1 - 1 / math.sqrt(2))) / 2
    assert loss_set(inputs)["dgs"].item() == pytest.approx(expected, abs=1e-6)
    pred = WeightedLossSet(**dgs_only)
    assert pred(inputs)["dgs"].item() == pytest.approx(1 - 1 / math.sqrt(2), abs=1e-6)


@pytest.mark.parametrize("stop_grad", [True, False])
@pytest.mark.parametrize("term", ["sd", "dgs"])
@pytest.mark.parametrize("push", [False, True])
def test_gradient_block(stop_grad, term, push):
    inputs = _inputs()
    weights = dict(rgb_weight=0.0, ce_weight=0.0, sd_weight=0.0, dgs_weight=0.0)
    weights[f"{term}_weight"] = 1.0
    loss_set = WeightedLossSet(**weights, teacher_stop_grad=stop_grad, dgs_push_away=push)
    loss_set(inputs)[term].backward()
    student = inputs.fine.semantic if term == "sd" else inputs.fine.sample_semantic
    assert student.grad is not None and student.grad.abs().sum() > 0
    teacher_grad = inputs.teacher_at_rays.grad
    if stop_grad:
        assert teacher_grad is None
    else:
        assert teacher_grad is not None and teacher_grad.abs().sum() > 0


@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 2, 7), (37, 64, 5), (500, 16, 12)])
def test_any_ray_sample_and_channel_count(shape):
    num_rays, num_samples, channels = shape
    inputs = _inputs(num_rays, num_samples, channels, fine=False)
    for push in (False, True):
        terms = WeightedLossSet(dgs_push_away=push)(inputs)
        assert all(torch.isfinite(t) for t in terms.values())


def test_missing_inputs_are_config_errors():
    with pytest.raises(ConfigError, match="'ce' needs semantic scores and labels"):
        WeightedLossSet()(_inputs(logits=None))
    with pytest.raises(ConfigError, match="'sd' needs the teacher"):
        WeightedLossSet()(_inputs(teacher_at_rays=None))
    no_semantics = _inputs(fine=False, coarse=_rays(6, 8, 5, semantic=False))
    with pytest.raises(ConfigError, match="'sd' needs rendered semantic"):
        WeightedLossSet()(no_semantics)
    with pytest.raises(ConfigError, match="'dgs' needs per-sample"):
        WeightedLossSet(sd_weight=0.0)(no_semantics)
    assert set(WeightedLossSet(**RGB_ONLY)(no_semantics)) == {"rgb"}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(dgs_center="depth"), "pred_weights, gt_depth"),
        (dict(sd_weight=-0.1), "sd_weight=-0.1"),
        (dict(rgb_weight=float("nan")), "rgb_weight=nan"),
        (dict(dgs_window=-1), "dgs_window=-1"),
        (dict(rgb_weight=0.0, **RGB_ONLY), "nothing to train"),
    ],
)
def test_bad_options_are_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        WeightedLossSet(**kwargs)


def test_config_defaults_match_the_constructor():
    base = LossSetConfig()
    loss_set = WeightedLossSet()
    expected = {"rgb": base.rgb_weight, "ce": base.ce_weight, "sd": base.sd_weight, "dgs": base.dgs_weight}
    assert loss_set.weights == expected
    assert (loss_set.dgs_window, loss_set.dgs_center, loss_set.teacher_stop_grad) == (2, "pred_weights", True)
    assert [c().name for c in (RgbLossConfig, CeLossConfig, SdLossConfig, DgsLossConfig)] == ["rgb", "ce", "sd", "dgs"]


def test_label_free_is_colour_and_both_distillations_and_never_reads_labels():
    inputs = _inputs()
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.losses.plugin",), autoload=False))
    label_free = registry.build("loss", OmegaConf.structured(LabelFreeLossConfig))
    terms = label_free(inputs)
    expected = WeightedLossSet(ce_weight=0.0)(inputs)  # the dgs set's weights, without the cross-entropy
    assert set(terms) == {"rgb", "sd", "dgs"} and all(torch.equal(terms[k], expected[k]) for k in terms)
    ignored = dataclasses.replace(inputs, labels=torch.full_like(inputs.labels, IGNORE))
    assert all(torch.equal(label_free(ignored)[k], terms[k]) for k in terms)
    assert label_free.head_predicts is None and not label_free.needs_instances


def test_label_free_refuses_a_cross_entropy_and_keeps_gt_depth_centres():
    with pytest.raises(ConfigError, match=r"^loss.ce_weight=1.0: the label_free loss set trains without labels; "
                                          r"expected 0 \(a loss set with the cross-entropy: \+loss=dgs\)$"):
        LabelFreeLossSet(ce_weight=1.0)
    assert LabelFreeLossSet(dgs_center="gt_depth").needs_labels is False  # depth is not a label


def test_needs_labels_follows_the_cross_entropy_weight():
    assert WeightedLossSet(**{**RGB_ONLY, "sd_weight": 0.25}).needs_labels is False
    assert WeightedLossSet(ce_weight=0.5).needs_labels is True
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.losses.plugin",), autoload=False))
    assert registry.build("loss", {"name": "instance"}).needs_labels is True  # instance ids are labels


def test_the_image_set_adds_d_ssim_on_whole_images_and_is_zero_for_a_perfect_render():
    from gpnerf_core.testing.inputs import loss_inputs
    from gpnerf_plugins.losses.sets import ImageLossConfig

    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.losses.plugin",), autoload=False))
    loss_set = registry.build("loss", OmegaConf.structured(ImageLossConfig))
    assert set(loss_set.weights) == {"rgb", "ce", "ssim"} and loss_set.needs_whole_images
    inputs = loss_inputs(semantics=True, sample_semantics=False, fine=False, whole_image=True)
    terms = loss_set(inputs)
    assert set(terms) == {"rgb", "ce", "ssim"} and float(terms["ssim"].detach()) > 0
    perfect = dataclasses.replace(inputs, output=dataclasses.replace(inputs.output, rgb=inputs.target_rgb.clone()))
    assert float(loss_set(perfect)["ssim"].detach()) == pytest.approx(0.0, abs=1e-6)
    colour_only = registry.build("loss", {"name": "image", "ce_weight": 0.0})
    assert not colour_only.needs_semantics and not colour_only.needs_labels
    with pytest.raises(ConfigError, match="the model renders random rays"):
        loss_set(loss_inputs(semantics=True, sample_semantics=False))


def official_3dgs_ssim(img1, img2, window_size=11):
    """3DGS's ``utils/loss_utils.py`` ``ssim`` (graphdeco-inria/gaussian-splatting), verbatim but for names:
    ``[N, C, H, W]``, size_average."""
    gauss = torch.tensor([math.exp(-(x - window_size // 2) ** 2 / float(2 * 1.5 ** 2)) for x in range(window_size)],
                         dtype=img1.dtype)
    gauss = gauss / gauss.sum()
    channel = img1.size(-3)
    window = gauss[:, None].mm(gauss[:, None].t())[None, None].expand(channel, 1, window_size, window_size)
    mu1 = F.conv2d(img1, window, padding=window_size // 2, groups=channel)
    mu2 = F.conv2d(img2, window, padding=window_size // 2, groups=channel)
    mu1_sq, mu2_sq, mu1_mu2 = mu1.pow(2), mu2.pow(2), mu1 * mu2
    sigma1_sq = F.conv2d(img1 * img1, window, padding=window_size // 2, groups=channel) - mu1_sq
    sigma2_sq = F.conv2d(img2 * img2, window, padding=window_size // 2, groups=channel) - mu2_sq
    sigma12 = F.conv2d(img1 * img2, window, padding=window_size // 2, groups=channel) - mu1_mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim_map = ((2 * mu1_mu2 + c1) * (2 * sigma12 + c2)) / ((mu1_sq + mu2_sq + c1) * (sigma1_sq + sigma2_sq + c2))
    return ssim_map.mean()


def test_the_training_ssim_is_3dgs_official_zero_padded_one():
    """Issue 55: D-SSIM zero-pads like 3DGS's official code (kornia's metric reflect-pads, which differs at borders)."""
    from kornia.metrics import ssim as kornia_ssim
    from gpnerf_plugins.losses.terms import structural_dissimilarity

    gen = torch.Generator().manual_seed(0)
    pred, target = torch.rand(3, 20, 24, generator=gen, dtype=torch.float64), torch.rand(3, 20, 24, generator=gen,
                                                                                       dtype=torch.float64)
    official = 1.0 - official_3dgs_ssim(pred[None], target[None])
    assert float(structural_dissimilarity(pred, target)) == pytest.approx(float(official), rel=1e-12, abs=1e-12)
    reflect = 1.0 - kornia_ssim(pred[None], target[None], window_size=11, max_val=1.0).mean()
    assert abs(float(reflect) - float(official)) > 1e-4
