"""MVSplat's parts: Gaussians on their source pixels at their depth with MVSplat's scales, colour from harmonics in the
source camera's frame, a cost volume that finds a plane's depth, a multi-view Transformer that does not care about the
order of the views, and a family whose whole view is its Gaussians rasterized (kept Gaussians render the same)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gpnerf_core import ConfigError, SourceViews, project_points
from gpnerf_core.geometry.gaussians.harmonics import (
    SH_C0, colour_to_dc, quaternion_product, quaternions_of, sh_basis, sh_colours,
)
from gpnerf_core.geometry.gaussians.projection import rotation_matrices
from gpnerf_core.registry.components import get_registry
from gpnerf_core.testing.inputs import KIT_INTRINSICS, kit_parts, model_view
from gpnerf_plugins.families.mvsplat.adapter import GEOMETRY_CHANNELS, pixel_gaussians
from gpnerf_plugins.families.mvsplat.depth import candidate_depths, correlation_volume
from gpnerf_plugins.families.mvsplat.transformer import MultiViewTransformer
from ply_reader import read_ply
from pipeline_check import KIT_PARTS

HEIGHT, WIDTH = 32, 48


def random_rotations(count: int, seed: int = 0) -> torch.Tensor:
    q = torch.randn(count, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return rotation_matrices(q)


def sources(views: int = 2, baseline: float = 0.2) -> SourceViews:
    c2w = torch.eye(4).repeat(views, 1, 1)
    c2w[:, 0, 3] = torch.arange(views) * baseline
    return SourceViews(rgb=torch.rand(views, 3, HEIGHT, WIDTH), intrinsics=KIT_INTRINSICS.expand(views, 3, 3).clone(),
                       c2w=c2w)


def test_each_gaussian_sits_on_its_source_pixel_at_its_depth_with_mvsplats_scale():
    views = sources()
    raw = torch.zeros(2, GEOMETRY_CHANNELS + 3 * 4, HEIGHT, WIDTH)  # offsets sigmoid(0) - 0.5 = 0 pixels
    depth = 1.0 + 2.0 * torch.rand(2, HEIGHT, WIDTH)
    gaussians = pixel_gaussians(raw, depth, torch.full_like(depth, 0.5), depth, views, sh_degree=1, scale_min=0.5,
                                scale_max=15.0)
    assert gaussians.count == 2 * HEIGHT * WIDTH
    for view in range(2):
        mine = gaussians.view_of == view
        pixels, z = project_points(gaussians.means[mine], views.intrinsics[view:view + 1], views.c2w[view:view + 1])
        rows, cols = torch.meshgrid(torch.arange(HEIGHT.__float__()), torch.arange(WIDTH.__float__()), indexing="ij")
        assert torch.allclose(pixels[0], torch.stack([cols, rows], -1).reshape(-1, 2), atol=1e-3)
        assert torch.allclose(z[0], depth[view].reshape(-1), atol=1e-5)
    footprint = 0.1 * (1 / KIT_INTRINSICS[0, 0] + 1 / KIT_INTRINSICS[1, 1])
    expected = (0.5 + 14.5 * 0.5) * depth.reshape(-1) * footprint
    assert torch.allclose(gaussians.scales, expected[:, None].expand(-1, 3), rtol=1e-5)


def test_colour_is_the_harmonics_seen_in_the_source_frame():
    colour = torch.tensor([[0.2, 0.5, 0.9]])
    dc = torch.zeros(1, 3, 4)
    dc[..., 0] = colour_to_dc(colour)
    assert torch.allclose(sh_colours(dc, torch.randn(1, 3)), colour, atol=1e-6)  # degree 0: any direction
    assert torch.allclose(sh_basis(torch.tensor([[0.0, 0.0, 1.0]]), 0), torch.tensor([[SH_C0]]))
    # A view-dependent colour turns with its source camera: rotate camera and viewer together, the colour stays.
    coefficients = torch.randn(5, 3, 9, dtype=torch.float64)
    rotation = random_rotations(1, seed=3)[0]
    direction = torch.randn(5, 3, dtype=torch.float64)
    raw = torch.zeros(1, GEOMETRY_CHANNELS + 27, 1, 5, dtype=torch.float64)
    raw[0, GEOMETRY_CHANNELS:, 0] = coefficients.reshape(5, 27).T
    colours = []
    for turn in (torch.eye(3, dtype=torch.float64), rotation):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = turn
        view = SourceViews(rgb=torch.zeros(1, 3, 1, 5, dtype=torch.float64),
                           intrinsics=KIT_INTRINSICS[None].double(), c2w=c2w[None])
        gaussians = pixel_gaussians(raw, torch.ones(1, 1, 5, dtype=torch.float64), torch.ones(1, 1, 5),
                                    torch.ones(1, 1, 5), view, sh_degree=2, scale_min=0.5, scale_max=15.0)
        colours.append(gaussians.colours(gaussians.means - direction @ turn.T))  # the viewer turned with the camera
    assert torch.allclose(colours[0], colours[1], atol=1e-9)


def test_camera_rotations_become_quaternions_that_compose():
    rotations = random_rotations(64)
    q = quaternions_of(rotations)
    assert torch.allclose(rotation_matrices(q), rotations, atol=1e-9) and (q[:, 0] >= 0).all()
    for a, b in ((0, 1), (2, 3)):
        product = rotation_matrices(quaternion_product(q[a:a + 1], q[b:b + 1]))[0]
        assert torch.allclose(product, rotations[a] @ rotations[b], atol=1e-9)
    assert torch.allclose(quaternions_of(torch.diag(torch.tensor([1.0, -1.0, -1.0]))[None].double()),
                          torch.tensor([[0.0, 1.0, 0.0, 0.0]], dtype=torch.float64))  # trace -1: no division by w


def test_the_cost_volume_peaks_at_the_depth_of_a_textured_plane():
    views, near, far, count = sources(baseline=0.4), 1.0, 4.0, 8
    depths = candidate_depths(near, far, count, torch.zeros(1))
    assert torch.allclose(1 / depths, torch.linspace(1 / near, 1 / far, count))  # uniform in inverse depth
    rows, cols = HEIGHT // 4, WIDTH // 4
    texture = torch.randn(1, 16, rows, cols * 3, generator=torch.Generator().manual_seed(1))
    for plane in (2, 5):
        # The second camera sits 0.4 m to the right: a plane at depth d moves f b / d pixels left in its image.
        shift_cells = KIT_INTRINSICS[0, 0] * 0.4 / depths[plane] / 4
        grid_x = (torch.arange(cols) + cols).float()[None].expand(rows, cols)
        first = texture[..., cols:2 * cols]
        second = F.grid_sample(texture, torch.stack([(2 * (grid_x + shift_cells) + 1) / (3 * cols) - 1,
                                                     (2 * torch.arange(rows).float()[:, None].expand(rows, cols) + 1)
                                                     / rows - 1], -1)[None], align_corners=False)
        volume = correlation_volume(torch.cat([first, second]), views, near, far, count)
        inside = slice(0, cols - 3)  # columns whose match lies inside the second view at every candidate
        assert volume[0, :, :, inside].mean(dim=(1, 2)).argmax() == plane


def test_the_transformer_does_not_care_about_the_order_of_the_views():
    torch.manual_seed(0)
    transformer = MultiViewTransformer(channels=8, layers=2, splits=2).eval()
    maps = torch.randn(3, 8, 4, 6)
    order = torch.tensor([2, 0, 1])
    assert torch.allclose(transformer(maps)[order], transformer(maps[order]), atol=1e-5)


def test_a_whole_view_is_its_gaussians_rasterized_and_kept_gaussians_render_the_same():
    model = get_registry().build("model", {"name": "mvsplat", "feature_dim": 8, "transformer_layers": 1,
                                           "depth_candidates": 4, "cost_unet_dim": 4, "depth_unet_dim": 4,
                                           "unet_levels": 2, "sh_degree": 1},
                                 parts=kit_parts(get_registry(), "mvsplat", head=True, parts=KIT_PARTS)).eval()
    camera, views = model_view()
    kept = model.encode_sources(views, near=camera.near, far=camera.far)
    fresh, again = model.predict(camera, views, stride=0, chunk_rays=1), model.predict(camera, None, stride=0,
                                                                                      chunk_rays=1, features=kept)
    assert fresh.stride == 2 and fresh.rgb.shape == (16, 24, 3) and fresh.semantic.shape[1:] == (16, 24)
    for name in ("rgb", "depth", "semantic", "logits"):
        assert torch.allclose(getattr(fresh, name), getattr(again, name), atol=1e-5), name
    with pytest.raises(ConfigError, match="multiples of 8 pixels"):
        model.check_image_size(36, 48)


def test_the_exported_3dgs_ply_renders_what_the_model_renders():
    from gpnerf_core.geometry.gaussians import Gaussians, rasterize_gaussians
    from gpnerf_core.geometry.gaussians.harmonics import sh_colours
    from gpnerf_core.runtime.ply import encode_ply

    torch.manual_seed(0)
    model = get_registry().build("model", {"name": "mvsplat", "feature_dim": 8, "transformer_layers": 1,
                                           "depth_candidates": 4, "cost_unet_dim": 4, "depth_unet_dim": 4,
                                           "unet_levels": 2, "sh_degree": 2},
                                 parts=kit_parts(get_registry(), "mvsplat", head=False, parts=KIT_PARTS)).eval()
    with torch.no_grad():  # view-dependent colour worth testing: the damped higher degrees made large
        model.depth.to_gaussians[-1].weight.mul_(30.0)
    camera, views = model_view()
    rig = torch.eye(4)  # the whole rig turned, so the source cameras' frames are not the world's
    rig[:3, :3] = random_rotations(1, seed=5)[0].float()
    rig[:3, 3] = torch.tensor([0.3, -0.2, 0.1])
    target = camera.c2w.clone()
    target[:3, 3] = torch.tensor([0.05, -0.03, 0.1])
    camera = type(camera)(camera.intrinsics, rig @ target, camera.height, camera.width, camera.near, camera.far)
    views = SourceViews(rgb=views.rgb, intrinsics=views.intrinsics, c2w=rig @ views.c2w)
    splats = model.scene_gaussians(views, near=camera.near, far=camera.far)
    columns = read_ply(encode_ply(splats.ply_columns()))
    assert list(columns)[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert list(columns)[-9:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
                                  "label"]
    rest = sorted((c for c in columns if c.startswith("f_rest_")), key=lambda c: int(c.rsplit("_", 1)[1]))
    assert len(rest) == 3 * 8  # degree 2: 8 coefficients beyond the first, per channel
    count = len(columns["x"])
    means = torch.from_numpy(np.stack([columns[a] for a in "xyz"], -1))
    dc = torch.from_numpy(np.stack([columns[f"f_dc_{c}"] for c in range(3)], -1))[:, :, None]
    higher = torch.from_numpy(np.stack([columns[c] for c in rest], -1)).reshape(count, 3, 8)
    colours = sh_colours(torch.cat([dc, higher], dim=-1), means - camera.c2w[:3, 3])
    scores = splats.labels  # label rendering: a Gaussian's label is its scores' argmax
    assert torch.equal(torch.from_numpy(columns["label"]).long(), scores)
    rasterized = rasterize_gaussians(
        Gaussians(means, torch.from_numpy(np.stack([columns[f"scale_{a}"] for a in range(3)], -1)).exp(),
                  torch.from_numpy(np.stack([columns[f"rot_{a}"] for a in range(4)], -1)),
                  torch.sigmoid(torch.from_numpy(columns["opacity"])), colours),
        intrinsics=camera.intrinsics, c2w=camera.c2w, height=camera.height, width=camera.width)
    assert torch.allclose(rasterized.features, model.predict(camera, views, stride=1, chunk_rays=1).rgb, atol=2e-4)


# ---- issue 55: made like the official MVSplat ---------------------------------------------------------------------


def test_cross_view_attention_reads_the_other_views_as_they_entered_the_block():
    """The official ``MultiViewFeatureTransformer`` builds the keys and values of a block's cross-attention from the
    previous block's output (``batch_features`` once per block), not from the views after the block's self-attention."""
    from gpnerf_plugins.families.mvsplat.transformer import window_position_embedding

    torch.manual_seed(0)
    transformer = MultiViewTransformer(channels=8, layers=1, splits=1).eval()
    maps = torch.randn(2, 8, 4, 6)
    x = (maps + window_position_embedding((4, 6), 8, maps.device)[None]).permute(0, 2, 3, 1).reshape(2, 1, 24, 8)
    self_attention, cross_attention = transformer.blocks[0]
    after_self = self_attention(x, x, None)
    expected = cross_attention(after_self, x.flip(0), None)  # two views: each one's "others" is the other's input
    got = transformer(maps).permute(0, 2, 3, 1).reshape(2, 1, 24, 8)
    assert torch.allclose(got, expected, atol=1e-6)
    assert not torch.allclose(got, cross_attention(after_self, after_self.flip(0), None), atol=1e-3)


def test_the_transformer_starts_xavier_uniform_and_blocks_past_the_sixth_as_identities():
    torch.manual_seed(0)
    channels = 64
    transformer = MultiViewTransformer(channels=channels, layers=7, splits=2)
    bound = (6 / (2 * channels)) ** 0.5  # xavier-uniform of a square matrix; torch's default Linear is 1 / sqrt(C)
    weight = transformer.blocks[0][0].query.weight.detach()
    assert float(weight.abs().max()) <= bound and float(weight.abs().max()) > 1.2 / channels ** 0.5
    for index, (self_attention, cross_attention) in enumerate(transformer.blocks):
        zero = index >= 6
        for norm in (self_attention.norm, cross_attention.norm_out):
            assert bool((norm.weight == 0).all()) == zero and bool((norm.weight == 1).all()) != zero


def test_the_unets_are_mvsplats_post_norm_ldm_layout_and_start_as_their_skip_paths():
    from gpnerf_plugins.families.mvsplat.depth import DepthPredictor, ResidualBlock, UNet

    torch.manual_seed(0)
    block = ResidualBlock(8)
    x = torch.randn(2, 8, 6, 8)
    assert torch.equal(block(x), x)  # the zero-initialised final GroupNorm: the block starts as its skip path
    assert isinstance(block.in_layers[0], torch.nn.Conv2d) and isinstance(block.in_layers[1], torch.nn.GroupNorm)
    unet = UNet(8, levels=3)
    assert isinstance(unet.stem, torch.nn.Conv2d) and len(unet.middle) == 2 and len(unet.decoder) == 6
    assert sum(isinstance(m, ResidualBlock) for m in unet.encoder) == 3 and len(unet.upsample) == 2
    assert unet(torch.randn(2, 8, 12, 16)).shape == (2, 8, 12, 16)
    assert unet(torch.randn(1, 8, 6, 10)).shape == (1, 8, 6, 10)  # sides that do not halve evenly
    predictor = DepthPredictor(feature_dim=8, candidates=4, cost_dim=32, depth_dim=32, levels=2, raw_channels=5)
    assert predictor.cost_refine[1].num_groups == 8 and predictor.depth_refine[1].num_groups == 4


def test_an_mvsplat_checkpoint_of_the_structure_before_issue_55_is_refused_in_one_line():
    from gpnerf_core import DataError
    from gpnerf_core.model.weights import load_weights

    model = get_registry().build("model", {"name": "mvsplat", "feature_dim": 8, "transformer_layers": 1,
                                           "depth_candidates": 4, "cost_unet_dim": 4, "depth_unet_dim": 4,
                                           "unet_levels": 2, "sh_degree": 1},
                                 parts=kit_parts(get_registry(), "mvsplat", head=False, parts=KIT_PARTS))
    weights = model.state_dict()
    load_weights(model, weights, "checkpoint new.pt")  # its own structure loads
    old = dict(weights)
    old["depth.cost_refine.3.middle.body.0.weight"] = torch.zeros(4)
    with pytest.raises(DataError, match=r"^checkpoint old\.pt is an mvsplat model from before issue 55's structure "
                                        r".*retrain") as caught:
        load_weights(model, old, "checkpoint old.pt")
    assert "\n" not in str(caught.value)
