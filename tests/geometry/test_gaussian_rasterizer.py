"""The Gaussian rasterizer against references written here: an explicit EWA projection (quaternion rotations by
quaternion products, J from autograd of the pinhole map), a dense compositor (every Gaussian against every pixel,
globally depth sorted, one Gaussian at a time) and central differences; plus the edge cases a model family hits."""

import subprocess
import sys

import pytest
import torch

from gpnerf_core.errors import ConfigError, NonFiniteError
from gpnerf_core.geometry.gaussians import Gaussians, choose_backend, rasterize_gaussians
from gpnerf_core.geometry.gaussians.projection import project_gaussians

HEIGHT, WIDTH = 24, 32
FIELDS = ("means", "scales", "rotations", "opacities", "features")

pytestmark = pytest.mark.usefixtures("one_thread")  # the numba pool follows torch's threads; the CI has 2 cores


@pytest.fixture(params=["torch", "numba"])
def backend(request):
    if request.param == "numba":
        pytest.importorskip("numba")
    return request.param


def camera(dtype=torch.float64, height=HEIGHT, width=WIDTH):
    """An off-centre pinhole and a turned, moved camera (so W is not the identity)."""
    intrinsics = torch.tensor([[28.0, 0.0, (width - 1) / 2 + 0.7], [0.0, 30.0, (height - 1) / 2 - 0.4], [0, 0, 1]],
                              dtype=dtype)
    angle = torch.tensor(0.3, dtype=dtype)
    c2w = torch.eye(4, dtype=dtype)
    c2w[:3, :3] = torch.tensor([[torch.cos(angle), 0, torch.sin(angle)], [0, 1, 0], [-torch.sin(angle), 0,
                                                                                   torch.cos(angle)]], dtype=dtype)
    c2w[:3, 3] = torch.tensor([0.4, -0.2, 0.1], dtype=dtype)
    return intrinsics, c2w


def scene(count, channels, seed, dtype=torch.float64, spread=4.0, pixels=(0.5, 3.0), opacity=(0.05, 0.95),
          height=HEIGHT, width=WIDTH, opaque=0):
    """``count`` Gaussians whose centres project around the image (``spread`` px beyond its edges), 1.5-5 m deep,
    with standard deviations of ``pixels`` px (per axis) and random rotations; the first ``opaque`` ones are centred on
    pixel centres with opacity 1 (the 0.99 cap binds there)."""
    gen = torch.Generator().manual_seed(seed)
    intrinsics, c2w = camera(dtype, height, width)

    def uniform(low, high, *shape):
        return low + (high - low) * torch.rand(*shape, generator=gen, dtype=dtype)

    z = uniform(1.5, 5.0, count)
    u, v = uniform(-spread, width - 1 + spread, count), uniform(-spread, height - 1 + spread, count)
    u[:opaque], v[:opaque] = u[:opaque].round().clamp(0, width - 1), v[:opaque].round().clamp(0, height - 1)
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(intrinsics).T
    means = (rays * z[:, None]) @ c2w[:3, :3].T + c2w[:3, 3]
    scales = uniform(*pixels, count, 3) * z[:, None] / 29.0
    opacities = uniform(*opacity, count)
    opacities[:opaque] = 1.0
    return Gaussians(means, scales, torch.randn(count, 4, generator=gen, dtype=dtype), opacities,
                     torch.randn(count, channels, generator=gen, dtype=dtype)), intrinsics, c2w


# ----------------------------------------------------------------------------------------------------- references


def quaternion_rotation(q):
    """``[G, 3, 3]``: column k is ``q e_k q*`` for the normalised q (quaternion products, not the closed form)."""
    q = q / q.norm(dim=-1, keepdim=True)

    def product(a, b):
        aw, ax, ay, az = a.unbind(-1)
        bw, bx, by, bz = b.unbind(-1)
        return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)

    conjugate = q * torch.tensor([1, -1, -1, -1], dtype=q.dtype)
    columns = [product(product(q, torch.eye(4, dtype=q.dtype)[k + 1].expand_as(q)), conjugate)[:, 1:] for k in range(3)]
    return torch.stack(columns, dim=-1)


def reference_projection(gaussians, intrinsics, c2w, height, width):
    """Centres, conics (``torch.linalg.inv``) and official radii, one explicit step at a time."""
    w2c = torch.linalg.inv(c2w)
    camera_points = gaussians.means @ w2c[:3, :3].T + w2c[:3, 3]
    centres, conics, radii = [], [], []
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    sigma = quaternion_rotation(gaussians.rotations) @ torch.diag_embed(gaussians.scales**2) \
        @ quaternion_rotation(gaussians.rotations).transpose(1, 2)
    limits_x = (-(cx + 0.5) / fx - 0.3 * tan_x, (width - 0.5 - cx) / fx + 0.3 * tan_x)
    limits_y = (-(cy + 0.5) / fy - 0.3 * tan_y, (height - 0.5 - cy) / fy + 0.3 * tan_y)
    for point, covariance in zip(camera_points, sigma):
        x, y, z = point
        centres.append(torch.stack([fx * x / z + cx, fy * y / z + cy]))
        clamped = torch.stack([z * torch.clamp(x / z, *limits_x), z * torch.clamp(y / z, *limits_y), z])
        jacobian = torch.autograd.functional.jacobian(lambda p: (intrinsics @ p)[:2] / p[2], clamped, create_graph=True)
        cov2d = jacobian @ w2c[:3, :3] @ covariance @ w2c[:3, :3].T @ jacobian.T + 0.3 * torch.eye(2, dtype=z.dtype)
        inverse = torch.linalg.inv(cov2d)
        conics.append(torch.stack([inverse[0, 0], inverse[0, 1], inverse[1, 1]]))
        mid, det = 0.5 * (cov2d[0, 0] + cov2d[1, 1]), torch.linalg.det(cov2d)
        radii.append(torch.ceil(3 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1)))))
    return torch.stack(centres), torch.stack(conics), camera_points[:, 2], torch.stack(radii)


def dense_reference(gaussians, intrinsics, c2w, height, width, background=None, near=0.01):
    """Every Gaussian in front against every pixel, globally sorted by (depth, index), one Gaussian at a time."""
    centres, conics, depths, _ = reference_projection(gaussians, intrinsics, c2w, height, width)
    v, u = torch.meshgrid(torch.arange(height, dtype=centres.dtype), torch.arange(width, dtype=centres.dtype),
                          indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    channels = gaussians.features.shape[1]
    transmittance, done = torch.ones_like(u), torch.zeros_like(u, dtype=torch.bool)
    features, depth = torch.zeros(u.shape[0], channels, dtype=u.dtype), torch.zeros_like(u)
    order = sorted(range(len(depths)), key=lambda i: (float(depths[i].detach()), i))
    for i in order:
        if depths[i] <= near:
            continue
        dx, dy = centres[i, 0] - u, centres[i, 1] - v
        power = -0.5 * (conics[i, 0] * dx * dx + conics[i, 2] * dy * dy) - conics[i, 1] * dx * dy
        alpha = torch.clamp(gaussians.opacities[i] * torch.exp(power), max=0.99)
        used = (power <= 0) & (alpha >= 1 / 255) & ~done
        stop = used & (transmittance * (1 - alpha) < 1e-4)
        done, used = done | stop, used & ~stop
        weight = torch.where(used, alpha * transmittance, torch.zeros_like(alpha))
        features = features + weight[:, None] * gaussians.features[i]
        depth = depth + weight * depths[i]
        transmittance = torch.where(used, transmittance * (1 - alpha), transmittance)
    if background is not None:
        features = features + background * transmittance[:, None]
    return (features.reshape(height, width, channels), depth.reshape(height, width),
            1 - transmittance.reshape(height, width))


def margins(gaussians, intrinsics, c2w, height, width):
    """The smallest relative distance of any (pixel, Gaussian) to the 1/255 skip, the 0.99 cap and any pixel's
    transmittance to the 1e-4 stop: a finite-difference step must stay well inside it."""
    centres, conics, _, _ = (t.detach() for t in reference_projection(gaussians, intrinsics, c2w, height, width))
    v, u = torch.meshgrid(torch.arange(height, dtype=centres.dtype), torch.arange(width, dtype=centres.dtype),
                          indexing="ij")
    dx, dy = centres[:, 0, None, None] - u, centres[:, 1, None, None] - v
    power = -0.5 * (conics[:, 0, None, None] * dx * dx + conics[:, 2, None, None] * dy * dy) \
        - conics[:, 1, None, None] * dx * dy
    raw = gaussians.opacities[:, None, None] * torch.exp(power)
    used = torch.where(raw >= 1 / 255, raw.clamp(max=0.99), torch.zeros_like(raw))
    lowest_t = torch.prod(1 - used, dim=0).min()
    return min(float((raw * 255 - 1).abs().min()), float((raw / 0.99 - 1).abs().min()), float(lowest_t / 1e-4 - 1))


def render(gaussians, intrinsics, c2w, backend, **kwargs):
    kwargs = {"height": HEIGHT, "width": WIDTH, **kwargs}
    return rasterize_gaussians(gaussians, intrinsics=intrinsics, c2w=c2w, backend=backend, **kwargs)


# -------------------------------------------------------------------------------------------------------- tests


def test_projection_is_the_explicit_ewa_projection_with_the_official_jacobian_clamp():
    gaussians, intrinsics, c2w = scene(40, 1, seed=1, spread=25.0, pixels=(0.3, 6.0))  # some beyond the 1.3 limits
    projected = project_gaussians(gaussians, intrinsics, c2w, HEIGHT, WIDTH, near=0.01)
    centres, conics, depths, radii = reference_projection(gaussians, intrinsics, c2w, HEIGHT, WIDTH)
    torch.testing.assert_close(projected.means2d, centres, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(projected.conics, conics, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(projected.depths, depths, rtol=1e-12, atol=1e-12)
    visible = projected.visible
    assert 0 < int(visible.sum()) < 40  # some centres are far enough outside to be culled
    assert torch.equal(projected.radii[visible].double(), radii[visible])
    assert (projected.radii[~visible] == 0).all()


DENSE = {"pixels": (1.5, 5.0), "opacity": (0.3, 0.95)}
"""A crowded scene: many pixels stop on the 1e-4 rule."""


@pytest.mark.parametrize("count, channels, seed", [(5, 3, 0), (60, 4, 1), (200, 2, 2)])
@pytest.mark.parametrize("tile_size", [8, 16])
def test_backends_equal_the_dense_reference(backend, count, channels, seed, tile_size):
    gaussians, intrinsics, c2w = scene(count, channels, seed, **(DENSE if count == 200 else {}))
    background = torch.linspace(-1, 1, channels, dtype=torch.float64)
    out = render(gaussians, intrinsics, c2w, backend, tile_size=tile_size, background=background)
    features, depth, alpha = dense_reference(gaussians, intrinsics, c2w, HEIGHT, WIDTH, background)
    assert out.backend == backend
    torch.testing.assert_close(out.features, features, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(out.depth, depth, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(out.alpha, alpha, rtol=1e-9, atol=1e-10)
    if count == 200:
        assert float((alpha > 1 - 1e-3).float().mean()) > 0.2  # many pixels stopped on the 1e-4 rule


def test_backend_gradients_equal_the_dense_reference_gradients_where_pixels_stop(backend):
    """The backward pass at scale (200 Gaussians, pixels that stop, alphas held at the 0.99 cap) against autograd
    through the dense reference."""
    gaussians, intrinsics, c2w = scene(200, 3, seed=2, opaque=20, **DENSE)
    gen = torch.Generator().manual_seed(5)
    weights = [torch.randn(HEIGHT, WIDTH, *shape, generator=gen, dtype=torch.float64) for shape in ((3,), (), ())]

    def gradients(render_fn):
        leaves = Gaussians(*(getattr(gaussians, name).clone().requires_grad_() for name in FIELDS))
        outputs = render_fn(leaves)
        sum((weight * output).sum() for weight, output in zip(weights, outputs)).backward()
        return [getattr(leaves, name).grad for name in FIELDS]

    expected = gradients(lambda g: dense_reference(g, intrinsics, c2w, HEIGHT, WIDTH))
    found = gradients(lambda g: (lambda r: (r.features, r.depth, r.alpha))(render(g, intrinsics, c2w, backend,
                                                                                  tile_size=8)))
    for name, want, got in zip(FIELDS, expected, found):
        torch.testing.assert_close(got, want, rtol=1e-7, atol=1e-9, msg=lambda m: f"{name}: {m}")


def test_gradients_match_central_differences(backend):
    """float64, a few Gaussians over several tiles, no (pixel, Gaussian) near a skip, cap or stop threshold."""
    for seed in range(50):
        gaussians, intrinsics, c2w = scene(4, 2, seed, spread=-2.0, pixels=(1.0, 2.5), opacity=(0.3, 0.9),
                                           height=10, width=12)
        if margins(gaussians, intrinsics, c2w, 10, 12) > 1e-3:
            break
    else:
        pytest.fail("no seed keeps every pixel away from the thresholds")
    gen = torch.Generator().manual_seed(seed)
    weights = [torch.randn(10, 12, *shape, generator=gen, dtype=torch.float64) for shape in ((2,), (), ())]
    background = torch.tensor([0.3, -0.5], dtype=torch.float64)

    def loss(*tensors):
        out = render(Gaussians(*tensors[:5]), intrinsics, c2w, backend, height=10, width=12, tile_size=4,
                     background=tensors[5])
        return sum((w * o).sum() for w, o in zip(weights, (out.features, out.depth, out.alpha)))

    inputs = [getattr(gaussians, name).clone().requires_grad_() for name in FIELDS] + [background.requires_grad_()]
    analytic = torch.autograd.grad(loss(*inputs), inputs)
    step = 1e-6
    for index, (tensor, grad) in enumerate(zip(inputs, analytic)):
        numeric = torch.zeros_like(tensor)
        for element in range(tensor.numel()):
            shifted = [t.detach().clone() for t in inputs]
            shifted[index].view(-1)[element] += step
            plus = loss(*shifted)
            shifted[index].view(-1)[element] -= 2 * step
            numeric.view(-1)[element] = (plus - loss(*shifted)) / (2 * step)
        name = (*FIELDS, "background")[index]
        torch.testing.assert_close(grad, numeric, rtol=1e-5, atol=1e-7, msg=lambda m: f"{name}: {m}")


def test_numba_agrees_with_torch_in_float32():
    pytest.importorskip("numba")
    gaussians, intrinsics, c2w = scene(300, 35, seed=3, dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(HEIGHT, WIDTH, 35, generator=gen)
    results = {}
    for name in ("torch", "numba"):
        leaves = Gaussians(*(getattr(gaussians, field).clone().requires_grad_() for field in FIELDS))
        out = render(leaves, intrinsics, c2w, name)
        ((out.features * weights).sum() + out.depth.sum() + out.alpha.sum()).backward()
        results[name] = [out.features, out.depth, out.alpha] + [getattr(leaves, field).grad for field in FIELDS]
    for index, (numba, reference) in enumerate(zip(results["numba"], results["torch"])):
        scale = float(reference.detach().abs().max())
        tolerance = 1e-6 if index < 3 else 1e-4
        assert float((numba - reference).detach().abs().max()) <= tolerance * max(scale, 1.0), index


def test_half_precision_inputs_and_autocast_rasterize_in_float32(backend):
    """``train.precision=bf16`` runs the step under CPU autocast and may hand bfloat16 features: the rasterizer works
    in float32 whatever it is given, as it would in float32."""
    gaussians, intrinsics, c2w = scene(60, 4, seed=5, dtype=torch.float32)
    reference = render(gaussians, intrinsics, c2w, backend)
    half = Gaussians(*(getattr(gaussians, field).to(torch.bfloat16) for field in FIELDS))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under_autocast = render(gaussians, intrinsics, c2w, backend)
        from_half = render(half, intrinsics, c2w, backend)
    assert under_autocast.features.dtype == torch.float32 and torch.equal(under_autocast.features, reference.features)
    assert from_half.features.dtype == torch.float32
    assert torch.allclose(from_half.alpha, reference.alpha, atol=0.05)


def test_numba_is_deterministic_whatever_the_thread_count():
    pytest.importorskip("numba")
    gaussians, intrinsics, c2w = scene(200, 5, seed=4, dtype=torch.float32)
    threads = torch.get_num_threads()
    try:
        outputs = []
        for count in (1, 1, 3):
            torch.set_num_threads(count)
            leaves = Gaussians(*(getattr(gaussians, name).clone().requires_grad_() for name in FIELDS))
            out = render(leaves, intrinsics, c2w, "numba", tile_size=8)
            (out.features.sum() + out.depth.sum()).backward()
            outputs.append([out.features, out.depth, out.alpha, leaves.means.grad, leaves.features.grad])
    finally:
        torch.set_num_threads(threads)
    for other in outputs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(outputs[0], other))


@pytest.mark.parametrize("tile_size", [5, 16])
def test_the_numba_forward_keeps_the_tables_and_lists_each_tile_builds_for_its_backward(tile_size):
    """A forward with ``keep`` leaves each tile's local table and block lists (a tile of 5 px has partial blocks) where
    the backward reads them: the same as the tile builds without keeping them; a forward that keeps none renders the
    same, and a second backward through one graph gives the same gradients."""
    pytest.importorskip("numba")
    import numpy as np

    from gpnerf_core.geometry.gaussians.binning import bin_gaussians
    from gpnerf_core.geometry.gaussians.numba_backend import fill_tiles_numba, kernels

    gaussians, intrinsics, c2w = scene(150, 3, seed=6, dtype=torch.float32)
    projected = project_gaussians(gaussians, intrinsics, c2w, HEIGHT, WIDTH, 0.2)
    bins = bin_gaussians(projected, HEIGHT, WIDTH, tile_size, fill_tiles_numba)
    arrays = [t.detach().contiguous().numpy() for t in (projected.means2d, projected.conics, projected.opacities,
                                                        gaussians.features, projected.depths, bins.offsets, bins.ids)]
    tiles, per_tile = bins.offsets.shape[0] - 1, kernels().blocks_per_tile(tile_size)
    kept = (np.full((bins.count, 7), np.nan), np.full(bins.count * per_tile, -1, dtype=np.int32),
            np.full((tiles, per_tile), -1, dtype=np.int64))
    outputs = [np.empty((HEIGHT, WIDTH, 3), np.float32), *(np.empty((HEIGHT, WIDTH), t) for t in
                                                           (np.float32, np.float32, np.int32))]
    kernels().forward_tiles(np.arange(tiles), *arrays, HEIGHT, WIDTH, tile_size, *outputs, True, *kept)
    empty = (np.empty((0, 7)), np.empty(0, dtype=np.int32), np.empty((0, 0), dtype=np.int64))
    means2d, conics, opacities, _, _, offsets, ids = arrays
    tiles_x = -(-WIDTH // tile_size)
    for tile in range(tiles):
        y0, x0 = (tile // tiles_x) * tile_size, (tile % tiles_x) * tile_size
        columns, rows = min(tile_size, WIDTH - x0), min(tile_size, HEIGHT - y0)
        start, end = offsets[tile], offsets[tile + 1]
        table, lists, counts = kernels()._tile_lists(means2d, conics, opacities, ids, start, end, x0, y0, columns,
                                                     rows, tile, False, *empty)
        blocks = counts.shape[0]
        assert np.array_equal(kept[0][start:end], table)
        assert np.array_equal(kept[2][tile, :blocks], counts)
        held = kept[1][start * per_tile:start * per_tile + blocks * (end - start)].reshape(blocks, end - start)
        for block in range(blocks):
            assert np.array_equal(held[block, :counts[block]], lists[block, :counts[block]])
    leaves = Gaussians(*(getattr(gaussians, name).clone().requires_grad_() for name in FIELDS))
    out = render(leaves, intrinsics, c2w, "numba", tile_size=tile_size)
    loss = out.features.sum() + out.depth.sum() + out.alpha.sum()
    first = torch.autograd.grad(loss, [leaves.means, leaves.features], retain_graph=True)
    second = torch.autograd.grad(loss, [leaves.means, leaves.features])
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    unkept = [np.empty_like(output) for output in outputs]
    kernels().forward_tiles(np.arange(tiles), *arrays, HEIGHT, WIDTH, tile_size, *unkept, False, *empty)
    assert all(np.array_equal(a, b) for a, b in zip(outputs, unkept))


@pytest.mark.parametrize("tile_size", [5, 16])
def test_the_numba_counting_sort_lists_what_the_torch_binning_lists(tile_size):
    pytest.importorskip("numba")
    from gpnerf_core.geometry.gaussians.binning import bin_gaussians, fill_tiles
    from gpnerf_core.geometry.gaussians.numba_backend import fill_tiles_numba

    gaussians, intrinsics, c2w = scene(300, 1, seed=12, spread=10.0)
    projected = project_gaussians(gaussians, intrinsics, c2w, HEIGHT, WIDTH, near=0.01)
    ours, theirs = (bin_gaussians(projected, HEIGHT, WIDTH, tile_size, fill) for fill in (fill_tiles, fill_tiles_numba))
    assert ours.count > 300 and torch.equal(ours.offsets, theirs.offsets) and torch.equal(ours.ids, theirs.ids)


@pytest.mark.parametrize("tile_size", [5, 16])
def test_the_numba_projection_for_rendering_without_gradients_is_torchs(tile_size):
    pytest.importorskip("numba")
    from gpnerf_core.geometry.gaussians.binning import bin_gaussians, fill_tiles
    from gpnerf_core.geometry.gaussians.numba_backend import project_and_bin_numba

    gaussians, intrinsics, c2w = scene(300, 1, seed=13, spread=10.0, opaque=5)
    means = gaussians.means.clone()
    means[:3, 2] = -1.0  # behind the camera (world z here is close to camera z)
    gaussians = Gaussians(means, gaussians.scales, gaussians.rotations, gaussians.opacities, gaussians.features)
    torch_projected = project_gaussians(gaussians, intrinsics, c2w, HEIGHT, WIDTH, near=0.01)
    torch_bins = bin_gaussians(torch_projected, HEIGHT, WIDTH, tile_size, fill_tiles)
    ours, bins = project_and_bin_numba(gaussians, intrinsics, c2w, HEIGHT, WIDTH, 0.01, tile_size)
    visible = torch_projected.visible
    assert torch.equal(ours.visible, visible) and torch.equal(ours.radii, torch_projected.radii)
    assert (ours.culled_behind, ours.clamped) == (torch_projected.culled_behind, torch_projected.clamped)
    for name in ("means2d", "conics", "depths"):
        assert torch.allclose(getattr(ours, name)[visible], getattr(torch_projected, name)[visible], rtol=1e-10), name
    assert torch.equal(bins.offsets, torch_bins.offsets) and torch.equal(bins.ids, torch_bins.ids)
    with torch.no_grad():  # and rasterize_gaussians takes it when nothing needs a gradient
        fast = rasterize_gaussians(gaussians, intrinsics=intrinsics, c2w=c2w, height=HEIGHT, width=WIDTH,
                                   backend="numba", tile_size=tile_size)
    slow = rasterize_gaussians(Gaussians(means.requires_grad_(), *(getattr(gaussians, f) for f in FIELDS[1:])),
                               intrinsics=intrinsics, c2w=c2w, height=HEIGHT, width=WIDTH, backend="numba",
                               tile_size=tile_size)
    assert torch.allclose(fast.features, slow.features.detach(), atol=1e-12)


def test_no_gaussians_render_the_background(backend):
    empty = Gaussians(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0), torch.zeros(0, 3))
    background = torch.tensor([0.2, 0.4, 0.6], requires_grad=True)
    out = render(empty, *camera(torch.float32), backend, background=background)
    assert torch.equal(out.features, background.detach().expand(HEIGHT, WIDTH, 3))
    assert not out.alpha.any() and not out.depth.any() and out.means2d.shape == (0, 2)
    out.features.sum().backward()
    assert torch.equal(background.grad, torch.full((3,), float(HEIGHT * WIDTH)))


def test_gaussians_behind_or_on_the_camera_plane_are_culled_with_finite_gradients(backend):
    gaussians, intrinsics, c2w = scene(6, 3, seed=5)
    camera_points = torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.0, -2.0], [0.3, 0.1, 0.005], [0.0, 0.0, 0.0099],
                                  [0.2, -0.1, 3.0], [0.0, 0.0, 2.0]], dtype=torch.float64)  # on the camera plane,
    # behind it, nearer than near (twice), then two in view
    means = (camera_points @ c2w[:3, :3].T + c2w[:3, 3]).requires_grad_()
    scales = gaussians.scales.clone().requires_grad_()
    out = render(Gaussians(means, scales, *(getattr(gaussians, n) for n in FIELDS[2:])), intrinsics, c2w, backend)
    assert out.culled_behind == 4 and (out.radii[:4] == 0).all() and (out.radii[4:] > 0).all()
    (out.features.sum() + out.depth.sum()).backward()
    assert torch.isfinite(means.grad).all() and not means.grad[:4].any() and means.grad[4:].any()
    assert torch.isfinite(scales.grad).all()


def test_the_default_near_plane_is_the_official_0_2_m_with_and_without_gradients(backend):
    """Issue 55: the official 3DGS rasterizer culls at camera z <= 0.2 (``in_frustum``); 0.01 before."""
    gaussians, intrinsics, c2w = scene(4, 3, seed=5)
    camera_points = torch.tensor([[0.0, 0.0, 0.1], [0.01, 0.0, 0.199], [0.0, 0.01, 0.21], [0.2, -0.1, 3.0]],
                                 dtype=torch.float64)
    means = camera_points @ c2w[:3, :3].T + c2w[:3, 3]
    moved = Gaussians(means, *(getattr(gaussians, n) for n in FIELDS[1:]))
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            probe = Gaussians(means.clone().requires_grad_(grad), *(getattr(gaussians, n) for n in FIELDS[1:]))
            out = render(probe if grad else moved, intrinsics, c2w, backend)
        assert out.culled_behind == 2 and (out.radii[:2] == 0).all() and (out.radii[2:] > 0).all()


def test_all_behind_the_camera_is_an_empty_view(backend):
    gaussians, intrinsics, _ = scene(20, 3, seed=6)
    flipped = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))  # turned round: all behind
    out = render(gaussians, intrinsics, flipped, backend)
    assert out.culled_behind == 20 and not out.alpha.any() and not out.features.any()


def test_a_huge_gaussian_covers_the_image_and_degenerate_ones_are_clamped_not_fatal(backend):
    gaussians, intrinsics, c2w = scene(8, 3, seed=7)
    scales = gaussians.scales.clone()
    scales[0] = torch.tensor([50.0, 80.0, 60.0])  # metres at a few metres' depth: far wider than the image
    scales[1] = 0.0  # a point: Sigma' = 0 before the low-pass filter
    scales[2, 2] = 0.0  # a disc, seen edge-on below (its zero axis turned onto the image plane)
    rotations = gaussians.rotations.clone()
    rotations[2] = torch.tensor([2**-0.5, 0.0, 2**-0.5, 0.0])  # the local z axis along the world x axis
    c2w = torch.eye(4, dtype=torch.float64)
    means = gaussians.means.clone()
    means[2] = torch.tensor([0.0, 0.1, 3.0])  # in front of this camera, which looks down +z
    means[:2] = torch.tensor([[0.1, 0.0, 4.0], [0.05, 0.02, 2.0]])
    degenerate = Gaussians(means, scales, rotations, gaussians.opacities, gaussians.features)
    out = render(degenerate, intrinsics, c2w, backend, tile_size=8)
    reference = dense_reference(degenerate, intrinsics, c2w, HEIGHT, WIDTH)
    for got, want in zip((out.features, out.depth, out.alpha), reference):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-10)
    assert out.clamped == 2  # the point and the disc seen edge-on (rank one)
    assert float(out.alpha.min()) > 0 and out.radii[0] > max(HEIGHT, WIDTH)


def test_nan_or_inf_in_any_input_is_named(backend):
    gaussians, intrinsics, c2w = scene(5, 3, seed=8)
    for name in FIELDS:
        broken = getattr(gaussians, name).clone()
        broken.view(-1)[1] = float("nan") if name != "scales" else float("inf")
        values = {field: getattr(gaussians, field) for field in FIELDS} | {name: broken}
        with pytest.raises(NonFiniteError, match=name):
            render(Gaussians(**values), intrinsics, c2w, backend)
    with pytest.raises(NonFiniteError, match="c2w"):
        render(gaussians, intrinsics, c2w * float("nan"), backend)


@pytest.mark.parametrize("change, message", [
    ({"height": 24.0}, "height=24.0 \\(float\\): expected an int"),
    ({"width": True}, "width=True"),
    ({"tile_size": 8.5}, "tile_size=8.5"),
    ({"near": float("nan")}, "near=nan: expected a finite distance >= 0"),
    ({"near": float("inf")}, "near=inf"),
    ({"near": -0.5}, "near=-0.5"),
    ({"intrinsics": "zero focal"}, "fx=0, fy=0: expected focal lengths > 0"),
    ({"intrinsics": "negative focal"}, "fx=-28, fy=30"),
    ({"scales": -0.01}, "scales hold -0.01: expected standard deviations >= 0"),
    ({"opacities": 1.5}, "opacities span .*1.5.*: expected values in \\[0, 1\\]"),
    ({"opacities": -0.25}, "opacities span \\[-0.25"),
])
def test_bad_arguments_are_one_line_config_errors_naming_them_before_any_kernel(backend, change, message):
    """Each documented check (docs/rasterizer.md, "Checks"): a ConfigError naming the argument and its value, never
    numba's own error, a ZeroDivisionError or a silently empty image."""
    gaussians, intrinsics, c2w = scene(5, 3, seed=11)
    kwargs = {key: value for key, value in change.items() if key in ("height", "width", "tile_size", "near")}
    if "intrinsics" in change:
        intrinsics = intrinsics.clone()
        if change["intrinsics"] == "zero focal":
            intrinsics[0, 0] = intrinsics[1, 1] = 0.0
        else:
            intrinsics[0, 0] = -28.0
    values = {field: getattr(gaussians, field) for field in FIELDS}
    for field in ("scales", "opacities"):
        if field in change:
            values[field] = values[field].clone()
            values[field].view(-1)[2] = change[field]
    with pytest.raises(ConfigError, match=message) as caught:
        render(Gaussians(**values), intrinsics, c2w, backend, **kwargs)
    assert "\n" not in str(caught.value) and "rasterize" in str(caught.value)


def test_boundary_arguments_are_accepted(backend):
    """near 0, opacities exactly 0 and 1, zero scales and numpy integer sizes are valid (no refusal)."""
    import numpy as np
    gaussians, intrinsics, c2w = scene(5, 3, seed=12)
    opacities = gaussians.opacities.clone()
    opacities[0], opacities[1] = 0.0, 1.0
    scales = gaussians.scales.clone()
    scales[2] = 0.0
    out = render(Gaussians(gaussians.means, scales, gaussians.rotations, opacities, gaussians.features), intrinsics,
                 c2w, backend, near=0, height=np.int64(HEIGHT), width=WIDTH)
    assert out.alpha.shape == (HEIGHT, WIDTH)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scales_overflowing_the_dtype_are_a_non_finite_error_on_every_backend(backend, dtype):
    """docs/rasterizer.md promises a NonFiniteError for a covariance overflowing the dtype: with and without gradients
    (the numba backend renders without gradients by its own projection kernel, which counts what overflowed)."""
    gaussians, intrinsics, c2w = scene(5, 3, seed=13, dtype=dtype)
    scales = gaussians.scales.clone()
    scales[3] = 1e30 if dtype == torch.float32 else 1e200
    huge = Gaussians(gaussians.means, scales, gaussians.rotations, gaussians.opacities, gaussians.features)
    with pytest.raises(NonFiniteError, match="scales: the 2D covariance of 1 Gaussian\\(s\\) overflows"):
        with torch.no_grad():
            render(huge, intrinsics, c2w, backend)
    with pytest.raises(NonFiniteError, match="overflows"):
        render(Gaussians(huge.means, huge.scales.requires_grad_(), *(getattr(huge, n) for n in FIELDS[2:])),
               intrinsics, c2w, backend)


def test_half_precision_camera_and_gaussians_are_cast_never_reaching_numba(backend):
    """float16 everywhere (the Gaussians, the camera, the background) renders as float32 would, to float16's
    rounding of the inputs: the documented cast, so the numba kernels only ever see float32 or float64."""
    gaussians, intrinsics, c2w = scene(40, 3, seed=14, dtype=torch.float32)
    half = Gaussians(*(getattr(gaussians, field).half() for field in FIELDS))
    rounded = Gaussians(*(getattr(half, field).float() for field in FIELDS))
    out = render(half, intrinsics.half(), c2w.half(), backend, background=torch.ones(3, dtype=torch.float16))
    want = render(rounded, intrinsics.half().float(), c2w.half().float(), backend, background=torch.ones(3))
    assert out.features.dtype == torch.float32
    torch.testing.assert_close(out.features, want.features)


def test_unknown_or_unavailable_backends_are_config_errors():
    gaussians, intrinsics, c2w = scene(5, 3, seed=9)
    with pytest.raises(ConfigError, match="known: auto, torch, numba, gsplat"):
        render(gaussians, intrinsics, c2w, "cuda_magic")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="gsplat"):
            render(gaussians, intrinsics, c2w, "gsplat")
    assert choose_backend("auto", torch.device("cpu")) in ("numba", "torch")
    with pytest.raises(ConfigError, match="tile_size"):
        render(gaussians, intrinsics, c2w, "torch", tile_size=0)


def test_means2d_retain_grad_gives_the_view_space_gradient(backend):
    gaussians, intrinsics, c2w = scene(30, 3, seed=10)
    out = render(Gaussians(gaussians.means.clone().requires_grad_(), *(getattr(gaussians, n) for n in FIELDS[1:])),
                 intrinsics, c2w, backend)
    out.means2d.retain_grad()
    out.features.square().sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (30, 2)
    assert out.means2d.grad[out.radii > 0].abs().sum() > 0 and not out.means2d.grad[out.radii == 0].any()


def test_importing_the_rasterizer_does_not_import_numba():
    code = "import sys, gpnerf_core, gpnerf_core.geometry.gaussians; print('numba' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "False"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat runs on CUDA only")
def test_gsplat_agrees_with_the_torch_backend_on_cuda():
    pytest.importorskip("gsplat")
    gaussians, intrinsics, c2w = scene(200, 4, seed=11, dtype=torch.float32, opacity=(0.05, 0.9))
    cuda = Gaussians(*(getattr(gaussians, name).cuda() for name in FIELDS))
    ours = render(cuda, intrinsics.cuda(), c2w.cuda(), "torch")
    theirs = render(cuda, intrinsics.cuda(), c2w.cuda(), "gsplat")
    for got, want in ((theirs.features, ours.features), (theirs.depth, ours.depth), (theirs.alpha, ours.alpha)):
        torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-3)


def test_the_rasterizer_bench_prints_a_render_a_forward_and_a_backward_per_row(capsys):
    from gpnerf_core.tools.bench import rasterizer as bench

    assert bench.main(["counts=50", "channels=3", "backends=torch", "repeats=1", "size=32x48", "threads=1"]) == 0
    header, row = capsys.readouterr().out.splitlines()[1:3]
    assert header.split()[-6:] == ["no-grad", "ms", "forward", "ms", "fwd+bwd", "ms"]
    assert row.split()[:3] == ["torch", "50", "3"] and all(float(v) > 0 for v in row.split()[3:])
    assert bench.main(["count=5"]) == 2
