"""``model=mvsnerf`` (MVSNeRF + semantic head) and its parts: the contract kit on the family and the ``mvsnet``
extractor, the plane-sweep cost volume on a scene whose answer is known, alpha without the sample interval, the
image sizes its 3D U-Net cannot take, and the family with a head (GP-NeRF's decoding; refused without semantic maps)."""

import pytest
import torch

from gpnerf_core import (
    ConfigError, ReferenceFrustum, SourceViews, StepBatch, TargetCamera, TargetView, plane_sweep, variance_over_views,
)
from gpnerf_core.testing import plugin_checks
from gpnerf_plugins.extractors.mvsnet import MVSNetFeatures
from gpnerf_plugins.families.mvsnerf.model import MVSNeRF
from pipeline_check import KIT_PARTS

SMALL = {"model/mvsnerf": {"num_planes": 8, "width": 16, "feature_extractor": KIT_PARTS["feature_extractor"]}}
"""The kit's head decodes semantic maps, which its own extractor (mvsnet, checked on its own) does not make."""
CHECKS = [check for check in plugin_checks(["gpnerf_plugins.families.plugin", "gpnerf_plugins.extractors.plugin"],
                                           configs=SMALL)
          if check.component in ("model/mvsnerf", "feature_extractor/mvsnet")]

HEIGHT, WIDTH = 32, 48
INTRINSICS = torch.tensor([[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])


def pose(x: float) -> torch.Tensor:
    """A camera at ``(x, 0, 0)`` looking down +z (OpenCV)."""
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return c2w


def texture(points: torch.Tensor) -> torch.Tensor:
    """``[N, 3]`` world points -> ``[N, 3]`` smooth colours of a pattern painted on a plane z = const."""
    x, y = points[:, 0], points[:, 1]
    return torch.stack(
        [0.5 + 0.4 * torch.sin(9 * x), 0.5 + 0.4 * torch.cos(7 * y), 0.5 + 0.2 * torch.sin(5 * x + 6 * y)], dim=-1)


def plane_image(c2w: torch.Tensor, depth: float) -> torch.Tensor:
    """``[3, H, W]`` image of the textured plane z = ``depth`` (world) seen by a camera of ``c2w`` (no rotation)."""
    v, u = torch.meshgrid(torch.arange(HEIGHT, dtype=torch.float32), torch.arange(WIDTH, dtype=torch.float32),
                          indexing="ij")
    rays = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3) @ torch.linalg.inv(INTRINSICS).T
    points = c2w[:3, 3] + rays * (depth - c2w[2, 3])
    return texture(points).T.reshape(3, HEIGHT, WIDTH)


@pytest.mark.parametrize("check", CHECKS, ids=str)
def test_the_contract_kit_passes_the_family_and_its_extractor(check, one_thread):
    check.run()


def test_a_view_swept_through_its_own_frustum_gives_back_its_map_at_every_plane():
    maps = torch.randn(2, 5, HEIGHT // 4, WIDTH // 4)
    frustum = ReferenceFrustum(INTRINSICS, pose(0.0), (HEIGHT, WIDTH), (HEIGHT // 4, WIDTH // 4), 0.5, 4.0, 8)
    sweep = plane_sweep(frustum, INTRINSICS.expand(2, 3, 3), torch.stack([pose(0.0), pose(0.0)]))
    warped = sweep.warp(maps)  # [2, 5, 8, 8, 12]
    assert bool(sweep.inside.all())
    assert torch.allclose(warped, maps[:, :, None].expand_as(warped), atol=1e-5)
    same = variance_over_views(sweep.warp(maps[:1].expand(2, -1, -1, -1)), sweep.inside)
    assert float(same.abs().max()) < 1e-8


def test_the_cost_is_lowest_on_the_plane_where_the_scene_is():
    """A textured fronto-parallel plane at 2 m seen by three cameras 0.2 m apart: the variance of their warped images
    over the views is smallest at the plane at 2 m (planes 0.25 m apart from 1 m to 3 m)."""
    cameras = torch.stack([pose(0.0), pose(-0.2), pose(0.2)])
    images = torch.stack([plane_image(c2w, 2.0) for c2w in cameras])
    frustum = ReferenceFrustum(INTRINSICS, cameras[0], (HEIGHT, WIDTH), (HEIGHT, WIDTH), 1.0, 3.0, 9)
    sweep = plane_sweep(frustum, INTRINSICS.expand(3, 3, 3), cameras)
    assert torch.allclose(frustum.depths()[4], torch.tensor(2.0))
    cost = variance_over_views(sweep.warp(images), sweep.inside)  # [3, 9, H, W]
    seen = sweep.inside.all(dim=0)  # voxels every view sees
    per_plane = torch.stack([cost[:, k][:, seen[k]].mean() for k in range(9)])
    assert int(per_plane.argmin()) == 4
    assert float(per_plane[4]) < 0.05 * float(torch.cat([per_plane[:4], per_plane[5:]]).min())


def test_a_volume_read_at_world_points_gives_its_voxels_values():
    """A volume holding each voxel's depth and pixel position, read at points of the (padded) frustum, gives back the
    points' depth and pixel (trilinear interpolation of functions linear in them is exact)."""
    frustum = ReferenceFrustum(INTRINSICS, pose(0.3), (HEIGHT, WIDTH), (HEIGHT // 4, WIDTH // 4), 0.5, 4.0, 8,
                               pad=(1, 2))
    planes, rows, cols = frustum.volume_size
    depths = frustum.depths()
    v = (torch.arange(-1, rows - 1) + 0.5) * 4 - 0.5
    u = (torch.arange(-2, cols - 2) + 0.5) * 4 - 0.5
    volume = torch.stack([depths[:, None, None].expand(-1, rows, cols), u.expand(planes, rows, cols),
                          v[:, None].expand(planes, rows, cols)])
    g = torch.Generator().manual_seed(0)
    # voxel centres span pixels -6.5 .. 53.5 (u) and -2.5 .. 33.5 (v) with the padding
    pixels = torch.rand(50, 2, generator=g) * torch.tensor([59.0, 35.0]) - torch.tensor([6.0, 2.0])
    depth = 0.5 + 3.5 * torch.rand(50, generator=g)
    rays = torch.cat([pixels, torch.ones(50, 1)], -1) @ torch.linalg.inv(INTRINSICS).T
    points = rays * depth[:, None] + pose(0.3)[:3, 3]
    read = frustum.sample(volume, frustum.coordinates(points))
    assert torch.allclose(read, torch.stack([depth, pixels[:, 0], pixels[:, 1]], -1), atol=1e-3)


def small_family(**options) -> MVSNeRF:
    settings = dict(num_classes=3, coarse_samples=8, fine_samples=0, volume_views=2, num_planes=8,
                    inverse_depth=False, pad=(0, 0), width=16)
    return MVSNeRF(extractor=MVSNetFeatures(), **{**settings, **options})


def target(far: float) -> StepBatch:
    """One target view between the two source views, rays from 1 m to ``far``."""
    sources = SourceViews(torch.rand(2, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(1)),
                          INTRINSICS.expand(2, 3, 3).clone(), torch.stack([pose(-0.1), pose(0.1)]))
    camera = TargetCamera(INTRINSICS, pose(0.0), HEIGHT, WIDTH, 1.0, far)
    view = TargetView(scene="s", frame=0, camera=camera, image=torch.rand(3, HEIGHT, WIDTH),
                      depth=torch.zeros(HEIGHT, WIDTH), labels=torch.zeros(HEIGHT, WIDTH, dtype=torch.long),
                      sources=sources, pixels=torch.tensor([[3.0, 4.0], [20.0, 17.0], [40.0, 30.0]]), render_seed=3)
    return StepBatch((view,))


def test_alpha_has_no_sample_interval(monkeypatch):
    """MVSNeRF's alpha = 1 - exp(-sigma): the same densities on samples twice as far apart give the same weights."""
    model = small_family().eval()
    sigma = torch.linspace(0.05, 0.6, 8)

    def constant(position, feature, direction):
        count = position.shape[0]
        return sigma.repeat(count // 8), torch.full((count, 3), 0.5), torch.zeros(count, 16)

    monkeypatch.setattr(model.mlp, "forward", constant)
    with torch.no_grad():
        near = model(target(far=2.0), semantics=False).views[0].coarse
        far = model(target(far=3.0), semantics=False).views[0].coarse
    assert torch.allclose(far.samples.depths - 1.0, 2 * (near.samples.depths - 1.0))  # the spacing doubled
    assert torch.allclose(near.weights, far.weights)
    assert torch.allclose(near.weights[:, 0], 1 - torch.exp(-sigma[0]))


def test_image_sizes_the_3d_unet_cannot_take_are_refused_in_one_line():
    model = small_family()
    model.check_image_size(96, 128)  # 24 x 32 cells
    model.check_image_size(32, 48)  # 8 x 12 cells: padded to 8 x 16
    with pytest.raises(ConfigError, match=r"image size 36x48 \(HxW\).*9x12 cells.*multiples of 8") as refused:
        model.check_image_size(36, 48)
    assert "\n" not in str(refused.value)
    with pytest.raises(ConfigError, match=r"model.num_planes=12.*multiple of 8"):
        small_family(num_planes=12)


def test_the_frustum_padding_is_a_minimum_raised_to_a_multiple_of_8():
    padded = small_family(pad=(4, 4))
    assert padded.volume_pad(24, 32, "96x128") == (4, 4)
    assert padded.volume_pad(8, 12, "32x48") == (4, 6)
    assert padded.volume_pad(60, 80, "240x320") == (6, 4)
    assert small_family().volume_pad(8, 12, "32x48") == (0, 2)


def test_a_target_with_fewer_views_than_the_network_was_built_for_renders_with_the_first_as_reference():
    model = small_family(volume_views=3).eval()
    batch = target(far=3.0)
    sources = batch.views[0].sources
    with torch.no_grad():
        output = model(batch, semantics=True).views[0].coarse
        encoded = model._encoded(sources, model.encode(sources.rgb), 1.0, 3.0)
    assert output.logits.shape == (3, 3) and bool(torch.isfinite(output.rgb).all())
    assert bool((output.weights.sum(-1) <= 1 + 1e-6).all())
    assert torch.equal(encoded.frustum.c2w, sources.c2w[0]) and encoded.volume.shape == (8, 8, 8, 16)


@pytest.mark.parametrize("fine_samples", [0, 4])
def test_with_a_head_it_renders_features_the_head_decodes_and_without_semantic_maps_it_is_refused(fine_samples,
                                                                                                  one_thread):
    from gpnerf_core.interfaces.model import SemanticMode
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.testing.inputs import kit_parts, model_batch, model_view

    registry = get_registry()
    node = {"name": "mvsnerf", "coarse_samples": 6, "fine_samples": fine_samples, "num_planes": 8, "width": 16}
    model = registry.build("model", node, parts=kit_parts(registry, "mvsnerf", head=True, parts=KIT_PARTS))
    channels = model.extractor.semantic_dim
    assert model.semantic_output.mode is SemanticMode.DECODED and model.mlp.semantic[-1].out_features == channels
    assert set(model.parameter_groups()) == {"feature_extractor", "transformer", "head"}
    batch = model_batch(sources=True)
    view = model(batch, semantics=True, sample_semantics=True).views[0]
    rays, last = batch.views[0].pixels.shape[0], view.last
    samples = 6 + fine_samples
    assert last.semantic.shape == (rays, channels) and last.sample_semantic.shape == (rays, samples, channels)
    assert last.logits is None and (view.fine is None or view.coarse.semantic is None)  # the last pass only
    assert view.teacher_at_rays.shape == (rays, channels)
    assert view.logits.shape == (1, model.head.num_outputs, 32, 48)
    camera, sources = model_view(sources=True)
    assert model.teacher_logits(batch.views[0].image).shape == (1, model.head.num_outputs, 32, 48)
    prediction = model.eval().predict(camera, sources, stride=0, chunk_rays=64)
    assert prediction.stride == 2 and prediction.semantic.shape == (channels, 16, 24)  # the semantic maps' grid
    assert prediction.logits.shape == (1, model.head.num_outputs, camera.height, camera.width)
    assert bool(torch.isfinite(prediction.logits).all())
    parts = kit_parts(registry, "mvsnerf", head=True, parts=KIT_PARTS)
    parts._cfg.model.feature_extractor = {"name": "mvsnet"}
    with pytest.raises(ConfigError, match=r"\+head=unet .*=mvsnet makes none \(model.feature_extractor.semantic=true, "
                                          r"or another extractor") as refused:
        registry.build("model", node, parts=parts)
    assert "\n" not in str(refused.value)
