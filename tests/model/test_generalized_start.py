"""Issue 54's start: a per-scene semantic 3DGS begun from what a generalizable model predicts for a scene (mvsplat's
Gaussians, GP-NeRF's rendered cells), merged and cut to a budget, its decoder begun from the model's (the identity
classifier for class scores, the head's weights for features), and the refusals and notes of bad input."""

from __future__ import annotations


import pytest
import torch

from gpnerf_core import (
    ConfigError,
    DataError,
    GaussianScene,
    begin_from_start,
    decode_checked,
    predict_start,
    start_overrides,
)
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.geometry.gaussians import Gaussians, rasterize_gaussians
from gpnerf_core.geometry.gaussians.harmonics import colour_to_dc, sh_colours
from gpnerf_core.geometry.point_fusion import backproject, rendered_view
from gpnerf_core.model.generalized_start import (
    CELL_SCALE,
    OPACITY_FLOOR,
    most_opaque,
    voxel_keep_opaque,
)
from gpnerf_core.registry.components import get_registry
from gpnerf_core.testing.inputs import KIT_HEAD, KIT_SAMPLES, kit_parts, model_scene
from pipeline_check import KIT_PARTS

MVSPLAT = {"name": "mvsplat", "feature_dim": 8, "transformer_layers": 1, "depth_candidates": 4, "cost_unet_dim": 4,
           "depth_unet_dim": 4, "unet_levels": 2, "sh_degree": 1}
CLASSES = ("wall", "floor", "chair")


class OneScene:
    """A dataset of the kit's synthetic scene (what ``FrameCache`` reads)."""

    def __init__(self) -> None:
        self.scene = model_scene()

    def load_scene(self, name: str):
        return self.scene


def inputs():
    dataset = OneScene()
    frames = FrameCache(dataset, torch.device("cpu"))
    selector = get_registry().build("view_selector", {"name": "nearest"})
    return frames, selector, dataset.scene


def mvsplat(head: bool):
    torch.manual_seed(0)
    return get_registry().build("model", MVSPLAT, parts=kit_parts(get_registry(), "mvsplat", head=head,
                                                                  parts=KIT_PARTS)).eval()


def gnt(head: bool = True):
    torch.manual_seed(0)
    return get_registry().build("model", {"name": "gnt", **KIT_SAMPLES},
                                parts=kit_parts(get_registry(), "gnt", head=head, parts=KIT_PARTS)).eval()


def started(start, *, head: bool, classes=None):
    """A semantic 3DGS sized by the start's overrides, begun from it; and its notes."""
    options = {"name": "semantic_3dgs", "feature_dim": start.feature_dim, "feature_levels": start.feature_levels,
               "feature_stride": start.feature_stride, "sh_degree": 1}
    model = get_registry().build("model", options, parts=kit_parts(get_registry(), "semantic_3dgs", head=head)).eval()
    return model, begin_from_start(model, start, classes)


def start_of(model, **options):
    frames, selector, scene = inputs()
    settings = {"num_source_views": 2, "budget": 100_000, "classes": CLASSES, "head_config": KIT_HEAD, **options}
    return predict_start(model, frames, selector, scene, **settings)


def camera_of(index: int):
    frames, _, scene = inputs()
    return frames.camera(scene, frames.frame(scene, index)), frames, scene


def rasterized(gaussians: GaussianScene, camera, stride: int = 1):
    """The start's own Gaussians rasterized: colour (degree 0 and 1 harmonics from the camera) then features."""
    from gpnerf_core.geometry.gaussians.rasterizer import strided_camera

    colours = sh_colours(gaussians.harmonics, gaussians.means - camera.c2w[:3, 3])
    intrinsics, height, width = strided_camera(camera, stride)
    out = rasterize_gaussians(Gaussians(gaussians.means, gaussians.scales, gaussians.rotations, gaussians.opacities,
                                        torch.cat([colours, gaussians.features], dim=-1)),
                              intrinsics=intrinsics, c2w=camera.c2w, height=height, width=width,
                              background=torch.zeros(3 + gaussians.features.shape[1]))
    return out.features


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a.clamp(0, 1) - b.clamp(0, 1)) ** 2).mean()))


# ---- predicting ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("head", [False, True])
def test_an_mvsplat_start_is_finite_within_budget_with_features_of_the_models_width(head):
    model = mvsplat(head)
    start = start_of(model)
    g = start.gaussians
    width = model.extractor.semantic_dim if head else 3  # the head's input, or K class scores
    assert start.semantics == ("features" if head else "scores") and g.features.shape == (g.count, width)
    assert start.frames == (0, 2) and start.family == "mvsplat" and 0 < g.count < start.predicted <= 2 * 32 * 48
    for name in ("means", "scales", "rotations", "opacities", "harmonics", "features"):
        assert torch.isfinite(getattr(g, name)).all(), name
    assert bool((g.opacities > OPACITY_FLOOR).all())
    assert start.feature_stride == (2 if head else 1) and start.feature_levels == (model.head.in_levels if head else 1)
    cut = start_of(model, budget=100)
    assert cut.gaussians.count == 100 and len(cut.notes) == 1
    assert "keeps the most opaque 100 of its" in cut.notes[0] and "model.max_gaussians" in cut.notes[0]
    kept = torch.sort(g.opacities, descending=True).values[:100]
    assert torch.equal(torch.sort(cut.gaussians.opacities, descending=True).values, kept)


def test_a_gnt_start_is_its_rendered_cells_with_the_heads_features():
    model = gnt()
    start = start_of(model, num_source_views=1, min_views=0, budget=300)
    g = start.gaussians
    assert start.semantics == "features" and g.features.shape == (g.count, model.extractor.semantic_dim)
    assert g.count == 300 and len(start.notes) == 1 and "300" in start.notes[0]
    assert torch.isfinite(torch.cat([g.means, g.scales, g.harmonics.flatten(1), g.features], dim=1)).all()
    assert bool((g.opacities >= 0.8).all()) and bool((g.opacities <= 0.99).all())  # a merged voxel's coverage
    assert torch.equal(g.scales[:, 0], g.scales[:, 2])  # isotropic
    camera, _, scene = camera_of(0)
    depth = (g.means - camera.c2w[:3, 3]) @ camera.c2w[:3, :3]  # camera frame of frame 0
    ratio = g.scales[:, 0] / depth[:, 2].abs()
    footprint = CELL_SCALE * start.feature_stride / float(camera.intrinsics[0, 0])
    assert float(ratio.max()) < 1.5 * footprint  # the cell's footprint at its depth (frame 2 sees it from 0.2 m away)
    assert bool(((depth.norm(dim=1) > scene.near) & (depth.norm(dim=1) < scene.far * 1.2)).all())
    agreeing = start_of(model, num_source_views=1, min_views=1)
    assert agreeing.predicted < start.predicted  # the agreement drops cells


def test_a_start_is_deterministic():
    model = mvsplat(False)
    first, second = start_of(model, budget=500), start_of(model, budget=500)
    for name in ("means", "scales", "rotations", "opacities", "harmonics", "features"):
        assert torch.equal(getattr(first.gaussians, name), getattr(second.gaussians, name)), name
    assert first.notes == second.notes


def test_a_per_scene_family_is_refused_naming_it():
    _, _, scene = inputs()
    model = get_registry().build("model", {"name": "semantic_3dgs"}, parts=kit_parts(get_registry(), "semantic_3dgs",
                                                                                   head=False))
    with pytest.raises(ConfigError, match="model=semantic_3dgs is a per-scene family"):
        start_of(model)


def test_merging_keeps_the_most_opaque_gaussian_of_each_voxel_whole():
    means = torch.tensor([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.5, 0.5], [0.03, 0.0, 0.0]])
    scene = GaussianScene(means=means, scales=torch.rand(4, 3), rotations=torch.randn(4, 4),
                          opacities=torch.tensor([0.3, 0.9, 0.5, 0.9]), harmonics=torch.randn(4, 3, 4),
                          labels=torch.arange(4), features=torch.randn(4, 5))
    merged = voxel_keep_opaque(scene, 0.1)
    assert merged.labels.tolist() == [1, 2]  # ties: the first; the kept one is a whole Gaussian, not a mean
    assert torch.equal(merged.features, scene.features[[1, 2]]) and torch.equal(merged.scales, scene.scales[[1, 2]])
    # it carries its voxel's coverage: 1 - (1 - 0.3)(1 - 0.9)(1 - 0.9) = 0.993, at most 0.99; a lone one its own
    assert torch.allclose(merged.opacities, torch.tensor([0.99, 0.5]))
    loose = GaussianScene(**{**scene.__dict__, "opacities": torch.tensor([0.3, 0.4, 0.5, 0.2])})
    assert torch.allclose(voxel_keep_opaque(loose, 0.1).opacities, torch.tensor([1 - 0.7 * 0.6 * 0.8, 0.5]))
    kept, note = most_opaque(scene, 2)
    assert kept.labels.tolist() == [1, 3] and "2 of its 4" in note
    assert most_opaque(scene, 4) == (scene, None)


# ---- handing over ----------------------------------------------------------------------------------------------------


def test_the_overrides_size_semantic_3dgs_for_the_start():
    scores = start_of(mvsplat(False))
    assert start_overrides(scores) == ["model.feature_dim=3", "model.feature_levels=1", "model.feature_stride=1"]
    features = start_of(mvsplat(True))
    overrides = start_overrides(features)
    assert overrides[:3] == [f"model.feature_dim={features.feature_dim}",
                             f"model.feature_levels={features.feature_levels}", "model.feature_stride=2"]
    assert overrides[3:] == ["+head=unet", "head.channels=16", "head.norm_groups=4"]


UNFILTERED = {"min_views": 0, "max_conflicts": 99}
"""No depth-map fusion: an untrained model's depths disagree between views, and these tests compare renders."""


def test_class_scores_begin_semantic_3dgs_rendering_the_start_exactly():
    model = mvsplat(False)
    start = start_of(model, **UNFILTERED)
    family, notes = started(start, head=False, classes=CLASSES)
    assert notes == [] and family.gaussians.size == start.gaussians.count
    assert torch.equal(family.classifier.weight[:, :, 0, 0], torch.eye(3)) and not family.classifier.bias.any()
    assert float(family.gaussians.extent) == pytest.approx(0.11)  # 1.1 x the cameras' radius
    camera, frames, scene = camera_of(0)
    own = family.predict(camera, None, stride=1, chunk_rays=0)
    direct = rasterized(start.gaussians, camera)
    assert torch.allclose(own.logits[0].permute(1, 2, 0), direct[..., 3:], atol=1e-5)  # identity: logits = scores
    assert torch.allclose(own.rgb, direct[..., :3], atol=1e-5)
    given = model.predict(camera, frames.source_views(scene, [0, 2]), stride=1, chunk_rays=0)
    assert psnr(own.rgb, given.rgb) > 30  # the merged start renders what mvsplat renders from all its Gaussians
    assert float((own.logits.argmax(1) == given.logits.argmax(1)).float().mean()) > 0.75


def test_features_begin_semantic_3dgs_with_the_models_head_at_its_stride():
    model = mvsplat(True)
    start = start_of(model, **UNFILTERED)
    family, notes = started(start, head=True, classes=CLASSES)
    assert notes == [] and family.feature_stride == 2
    for key, value in model.head.state_dict().items():
        assert torch.equal(family.head.state_dict()[key], value), key
    camera, frames, scene = camera_of(2)
    own = family.predict(camera, None, stride=1, chunk_rays=0)
    semantic = rasterized(start.gaussians, camera, stride=2)[..., 3:].permute(2, 0, 1)[None]
    assert tuple(own.semantic.shape[1:]) == (16, 24) and torch.allclose(own.semantic[None], semantic, atol=1e-5)
    expected = decode_checked(model.head, semantic, camera.image_size).logits  # the generalizable model's head
    assert torch.allclose(own.logits, expected, atol=1e-4)
    given = model.predict(camera, frames.source_views(scene, [2, 0]), stride=1, chunk_rays=0)
    assert psnr(own.rgb, given.rgb) > 30


def test_other_classes_keep_geometry_and_colour_and_start_the_decoder_afresh():
    start = start_of(mvsplat(False))
    torch.manual_seed(0)
    family, notes = started(start, head=False, classes=("sky", "road", "car"))
    assert len(notes) == 1 and "['wall', 'floor', 'chair']" in notes[0] and "['sky', 'road', 'car']" in notes[0]
    assert torch.equal(family.gaussians.means, start.gaussians.means)
    assert not torch.equal(family.classifier.weight[:, :, 0, 0], torch.eye(3))  # the fresh decoder's own start
    assert not torch.allclose(family.gaussians.features, start.gaussians.features)
    assert float(family.gaussians.features.detach().min()) >= -2.0  # RGB2SH(U(0, 1)), as a point start


def test_initialise_begins_from_a_set_start_and_a_budget_keeps_the_most_opaque(capsys):
    start = start_of(mvsplat(False))
    options = {"name": "semantic_3dgs", "feature_dim": 3, "sh_degree": 1, "density": "budgeted", "max_gaussians": 50}
    family = get_registry().build("model", options, parts=kit_parts(get_registry(), "semantic_3dgs", head=False))
    family.use_start(start, CLASSES)
    family.hooks.initialise(model_scene())
    assert family.gaussians.size == 50
    assert "keeps the most opaque 50 of its" in capsys.readouterr().err
    expected = torch.sort(start.gaussians.opacities, descending=True).values[:50]
    assert torch.allclose(torch.sort(torch.sigmoid(family.gaussians.opacity_logits), descending=True).values,
                          expected, atol=1e-6)
    family.hooks.initialise(model_scene())  # Gaussians already there win
    assert family.gaussians.size == 50


def test_feature_keys_are_checked_naming_them():
    for options, key in (({"feature_levels": 3}, "model.feature_levels=3"), ({"feature_stride": 0},
                                                                            "model.feature_stride=0")):
        with pytest.raises(ConfigError, match=key):
            get_registry().build("model", {"name": "semantic_3dgs", **options},
                                 parts=kit_parts(get_registry(), "semantic_3dgs", head=False))
    family = get_registry().build("model", {"name": "semantic_3dgs", "feature_stride": 5},
                                  parts=kit_parts(get_registry(), "semantic_3dgs", head=False))
    with pytest.raises(ConfigError, match="model.feature_stride=5"):
        family.check_image_size(32, 48)


def test_a_gnt_start_renders_what_gnt_rendered_at_its_training_frames():
    """Each training frame as GP-NeRF rendered it from the other: the started model's depth within 3 cm (median), its
    semantic map along GP-NeRF's (mean cosine > 0.87; the same features shuffled among the Gaussians: 0.80), its
    classes mostly the same (> 0.62; shuffled: 0.51), its colour above 17 dB (the kit's random texture, blurred by half
    a cell)."""
    model = gnt()
    start = start_of(model, num_source_views=1, min_views=0)
    family, _ = started(start, head=True, classes=CLASSES)
    cosine, agree = [], []
    for index in (0, 2):
        camera, frames, scene = camera_of(index)
        own = family.predict(camera, None, stride=start.feature_stride, chunk_rays=0)
        given = model.predict(camera, frames.source_views(scene, [2 - index]), stride=0, chunk_rays=4096)
        assert float((own.depth - given.depth).abs().median()) < 0.03 and psnr(own.rgb, given.rgb) > 17
        cosine.append(float(torch.nn.functional.cosine_similarity(own.semantic, given.semantic, dim=0).mean()))
        agree.append(float((own.logits.argmax(1) == given.logits.argmax(1)).float().mean()))
    assert sum(cosine) / 2 > 0.87 and sum(agree) / 2 > 0.62


def test_a_start_that_keeps_nothing_is_refused_naming_the_scene_and_frames():
    with pytest.raises(DataError, match=r"scene 'kit': model=gnt left no Gaussian to start from in training frames "
                                        r"\[0, 2\]"):
        start_of(gnt(), num_source_views=1, min_views=1, tolerance=1e-12)


def test_a_gnt_start_without_semantics_is_its_cells_colour_and_geometry():
    model = gnt(head=False)  # GP-NeRF's semantics are its head's: without one, colour and depth only
    start = start_of(model, num_source_views=1, min_views=0, every=2)  # frame 0 alone, rendered from frame 2
    assert start.semantics == "none" and start.gaussians.features is None and start_overrides(start) == []
    camera, frames, scene = camera_of(0)
    given = model.predict(camera, frames.source_views(scene, [2]), stride=0, chunk_rays=4096)
    view = rendered_view(given, camera)
    cells = backproject(view)
    rows = torch.cdist(start.gaussians.means, cells).argmin(dim=1)  # each kept Gaussian's own cell
    assert torch.allclose(start.gaussians.means, cells[rows], atol=1e-5)
    assert torch.allclose(start.gaussians.harmonics[:, :, 0], colour_to_dc(given.rgb.clamp(0, 1).reshape(-1, 3)[rows]),
                          atol=1e-5)
    footprint = CELL_SCALE * view.depth.reshape(-1)[rows] * given.stride / float(camera.intrinsics[0, 0])
    assert torch.allclose(start.gaussians.scales[:, 1], footprint, rtol=1e-4)
    family = get_registry().build("model", {"name": "semantic_3dgs", "feature_dim": 4, "sh_degree": 1},
                                  parts=kit_parts(get_registry(), "semantic_3dgs", head=False))
    assert begin_from_start(family, start, CLASSES) == [] and family.gaussians.size == start.gaussians.count
    assert not torch.equal(family.classifier.weight[:, :, 0, 0], torch.eye(3, 4))  # no start to begin it from


def test_a_start_that_keeps_little_says_which_rule_dropped_it():
    from types import SimpleNamespace

    from gpnerf_core.geometry.point_fusion import DepthView
    from gpnerf_core.geometry.rays import pixel_grid
    from gpnerf_core.model.generalized_start import fusion_note

    scene = SimpleNamespace(name="room", near=0.5, far=6.0)
    k = torch.tensor([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]])

    def part(depth: float, x: float):
        c2w = torch.eye(4)
        c2w[0, 3] = x
        view = DepthView(depth=torch.full((12, 16), depth), pixels=pixel_grid(12, 16, 1), intrinsics=k, c2w=c2w,
                         height=12, width=16)
        gaussians = GaussianScene(means=torch.zeros(192, 3), scales=torch.ones(192, 3), rotations=torch.randn(192, 4),
                                  opacities=torch.full((192,), 0.5), harmonics=torch.zeros(192, 3, 1),
                                  labels=torch.full((192,), -1))
        return gaussians, view

    at_far = [part(6.0, 0.0), part(6.0, 0.1)]  # every pixel at the far bound: the model's depth failed
    note = fusion_note(at_far, 0, scene, min_views=1, tolerance=0.1, max_conflicts=3)
    assert note.startswith("the start keeps 0 of the 384 Gaussians") and "384 at a depth bound" in note
    assert fusion_note([part(3.0, 0.0), part(3.0, 0.1)], 384, scene, min_views=1, tolerance=0.1,
                       max_conflicts=3) is None


# ---- the scene's own points, the model's semantics ---------------------------------------------------------------------


def test_a_point_takes_the_features_of_the_frames_that_see_it():
    from gpnerf_core.geometry.point_fusion import DepthView
    from gpnerf_core.geometry.rays import pixel_grid
    from gpnerf_core.model.generalized_start import point_features

    k = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])

    def frame(depth: float, feature: float):  # one 2 x 2 cell at the origin looking down +z, a surface at ``depth``
        view = DepthView(depth=torch.full((1, 1), depth), pixels=pixel_grid(2, 2, 2), intrinsics=k, c2w=torch.eye(4),
                         height=2, width=2)
        features = torch.full((1, 2), feature)
        return GaussianScene(means=torch.zeros(1, 3), scales=torch.ones(1, 3), rotations=torch.tensor([[1.0, 0, 0, 0]]),
                             opacities=torch.ones(1), harmonics=torch.zeros(1, 3, 1),
                             labels=torch.full((1,), -1, dtype=torch.long), features=features), view

    parts = [frame(2.0, 1.0), frame(0.5, 3.0)]  # the second frame's surface is in front of the first point
    points = torch.tensor([[0.5, 0.5, 1.0], [0.5, 0.5, 5.0], [100.0, 0.0, 1.0]])
    features = point_features(points, parts, tolerance=0.1)
    assert torch.equal(features[0], torch.tensor([1.0, 1.0]))  # seen by the first frame only
    assert torch.equal(features[1], torch.tensor([2.0, 2.0]))  # behind both surfaces: every frame it falls in
    assert torch.equal(features[2], torch.tensor([2.0, 2.0]))  # in no frame: the mean of every cell
    import dataclasses

    parts[1] = (dataclasses.replace(parts[1][0], features=None), parts[1][1])
    assert point_features(points, parts, tolerance=0.1) is None  # a model without semantics gives none


def test_a_points_start_is_the_scenes_points_with_the_models_features():
    from gpnerf_core.geometry.gaussians.initialisation import neighbour_scales, starting_points
    from gpnerf_core.model.generalized_start import points_start

    model = gnt()
    frames, selector, scene = inputs()
    torch.manual_seed(0)
    points, origin = starting_points(scene, 400, 2)
    start = points_start(model, frames, selector, scene, points, num_source_views=1, opacity=0.1, classes=CLASSES,
                         head_config=KIT_HEAD, origin=origin)
    g = start.gaussians
    assert start.geometry == "points" and start.semantics == "features" and start.predicted == points.count
    assert torch.equal(g.means, points.xyz.float()) and torch.allclose(g.opacities, torch.full((g.count,), 0.1))
    assert torch.equal(g.scales[:, 0], neighbour_scales(points.xyz.float()))
    assert torch.equal(g.scales[:, 0], g.scales[:, 2])
    assert torch.allclose(sh_colours(g.harmonics, g.means)[:, :3], points.rgb.float().clamp(0, 1), atol=1e-6)
    assert g.features.shape == (points.count, model.extractor.semantic_dim) and torch.isfinite(g.features).all()
    assert g.features.std(dim=0).max() > 0  # each point its own frames' features, not one mean
    family, notes = started(start, head=True, classes=CLASSES)
    assert notes == [] and family.gaussians.size == points.count
    for key, value in model.head.state_dict().items():
        assert torch.equal(family.head.state_dict()[key], value), key
