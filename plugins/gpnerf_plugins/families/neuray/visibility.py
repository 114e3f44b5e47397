"""NeuRay's visibility: a feature map G per source view, decoded into a mixture of logistics along each source ray.

``DepthInitNet`` (NeuRay's depth variant, which Semantic-Ray loads) makes an initial map G0 from a view's image, its
depth and how consistently that depth reprojects into the other views; ``VisibilityEncoder`` fuses G0 with the
image features into G; ``VisibilityDecoder`` reads G at a target sample's projection and gives the probability that
the source ray reaches the sample unoccluded (``vis``) and that it ends within the sample's interval (``hit``).

Depths along a source ray are in NeuRay's normalised inverse depth ``t`` (0 at near, 1 at far).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import SourceViews, pixel_grid, project_points

CONSISTENCY_CHANNELS = 8
"""Masked mean and variance over the other views of |delta RGB| (3) and |delta inverse depth| (1)."""
INVERSE_DEPTH_CLAMP = 1.5
"""|delta inverse depth| / inverse range is clamped here (NeuRay)."""


def normalized_inverse_depth(depth: Tensor, near: float, far: float) -> Tensor:
    """``t = (1/depth - 1/near) / (1/far - 1/near)``: 0 at ``near``, 1 at ``far``, increasing with depth (metres)."""
    return (1.0 / depth.clamp_min(1e-4) - 1.0 / near) / (1.0 / far - 1.0 / near)


def _bilinear(maps: Tensor, pixels: Tensor, mode: str = "bilinear") -> Tensor:
    """``maps`` ``[V, C, H, W]`` at ``pixels`` ``[V, N, 2]`` (u, v in pixels of those maps) -> ``[V, N, C]``."""
    height, width = maps.shape[-2:]
    scale = torch.tensor([2.0 / width, 2.0 / height], dtype=pixels.dtype, device=pixels.device)
    grid = ((pixels + 0.5) * scale - 1.0)[:, :, None, :]
    return F.grid_sample(maps, grid, mode=mode, align_corners=False)[..., 0].transpose(1, 2)


def consistency_features(sources: SourceViews, near: float, far: float) -> Tensor:
    """``[V, 8, H, W]``: each pixel of each view back-projected with its depth and projected into the other views,
    where the depth and colour found there are compared with its own (NeuRay's ``DepthInitNet`` input).

    Channels: masked mean and variance, over the other views that see the point and have a depth there, of
    ``|rgb_j - rgb_i|`` (3) and ``|1/z_j - 1/depth_j| / (1/near - 1/far)`` clamped at 1.5 (1). Pixels of unknown depth
    (0) and pixels no other view sees get zeros.
    """
    rgb, depth = sources.rgb, _depth_of(sources)
    views, _, height, width = rgb.shape
    pixels = pixel_grid(height, width, device=rgb.device)  # [N, 2]
    rays = torch.cat([pixels, torch.ones_like(pixels[:, :1])], -1) @ torch.linalg.inv(sources.intrinsics).transpose(1, 2)
    camera_points = rays * depth.reshape(views, -1, 1)  # [V, N, 3] in each view's camera
    world = camera_points @ sources.c2w[:, :3, :3].transpose(1, 2) + sources.c2w[:, None, :3, 3]
    projected, z = project_points(world.reshape(-1, 3), sources.intrinsics, sources.c2w)  # [V_j, V_i*N, .]
    seen_depth = _bilinear(depth[:, None], projected, mode="nearest")[..., 0]  # [V_j, V_i*N]
    seen_rgb = _bilinear(rgb, projected)  # [V_j, V_i*N, 3]
    inside = ((projected[..., 0] >= -0.5) & (projected[..., 0] <= width - 0.5) & (projected[..., 1] >= -0.5)
              & (projected[..., 1] <= height - 0.5))
    own = torch.eye(views, dtype=torch.bool, device=rgb.device).repeat_interleave(height * width, dim=1)
    known = (depth.reshape(1, -1) > 0)
    valid = (inside & (z > 1e-4) & (seen_depth > 0) & known & ~own).float()[..., None]  # [V_j, V_i*N, 1]
    inverse_range = 1.0 / near - 1.0 / far
    depth_error = ((1.0 / z.clamp_min(1e-4) - 1.0 / seen_depth.clamp_min(1e-4)).abs() / inverse_range)
    colour_error = (seen_rgb - rgb.permute(0, 2, 3, 1).reshape(1, -1, 3)).abs()
    errors = torch.cat([colour_error, depth_error.clamp(max=INVERSE_DEPTH_CLAMP)[..., None]], -1)  # [V_j, V_i*N, 4]
    count = valid.sum(0).clamp_min(1.0)
    mean = (errors * valid).sum(0) / count
    variance = (((errors - mean) ** 2) * valid).sum(0) / count
    features = torch.cat([mean, variance], -1)  # [V_i*N, 8]
    return features.reshape(views, height, width, CONSISTENCY_CHANNELS).permute(0, 3, 1, 2)


def _depth_of(sources: SourceViews) -> Tensor:
    """The sources' depth ``[V, H, W]``, zeros (unknown) where the dataset gave none."""
    if sources.depth is None:
        return sources.rgb.new_zeros(sources.rgb.shape[0], *sources.rgb.shape[-2:])
    return sources.depth.to(sources.rgb.dtype)


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with instance norm and a (projected where the shape changes) shortcut, as NeuRay's."""

    def __init__(self, in_dim: int, out_dim: int, stride: int = 1) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(in_dim, out_dim, 3, stride, 1, bias=False), nn.InstanceNorm2d(out_dim), nn.ReLU(inplace=True),
            nn.Conv2d(out_dim, out_dim, 3, 1, 1, bias=False), nn.InstanceNorm2d(out_dim))
        self.shortcut = (nn.Identity() if stride == 1 and in_dim == out_dim else
                         nn.Sequential(nn.Conv2d(in_dim, out_dim, 1, stride, bias=False), nn.InstanceNorm2d(out_dim)))

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.body(x) + self.shortcut(x))


class DepthInitNet(nn.Module):
    """G0 ``[V, dim, h, w]`` from each view's RGB, normalised inverse depth and its 8 consistency channels (12 in all),
    through a residual encoder-decoder to 1/4 resolution, plus a skip of the depth alone (NeuRay's ``DepthInitNet``).

    Simplified for CPU scale: the encoder has one residual block per stage (32 at 1/4, 64 at 1/8) where NeuRay's
    has 1/2/6 blocks of 32/64/128 channels down to 1/16.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3 + 1 + CONSISTENCY_CHANNELS, 32, 7, 2, 3, bias=False),
                                  nn.InstanceNorm2d(32), nn.ReLU(inplace=True))
        self.down4 = ResidualBlock(32, 32, stride=2)
        self.down8 = ResidualBlock(32, 64, stride=2)
        self.up4 = nn.Sequential(nn.Conv2d(64 + 32, dim, 3, 1, 1), nn.ReLU(inplace=True))
        self.depth_skip = nn.Sequential(nn.Conv2d(1, 8, 2, 2), nn.ReLU(inplace=True), nn.Conv2d(8, dim // 2, 2, 2))
        self.fuse = nn.Conv2d(dim + dim // 2, dim, 1)

    def forward(self, sources: SourceViews, near: float, far: float) -> Tensor:
        depth = _depth_of(sources)
        inverse = torch.where(depth > 0, normalized_inverse_depth(depth, near, far), torch.zeros_like(depth))[:, None]
        x = torch.cat([sources.rgb, inverse, consistency_features(sources, near, far)], 1)
        quarter = self.down4(self.stem(x))
        eighth = self.down8(quarter)
        up = F.interpolate(eighth, size=quarter.shape[-2:], mode="bilinear", align_corners=False)
        image = self.up4(torch.cat([up, quarter], 1))
        skip = F.interpolate(self.depth_skip(inverse), size=image.shape[-2:], mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([image, skip], 1))


class VisibilityEncoder(nn.Module):
    """G ``[V, dim, h, w]`` from the image features and G0: 3x3 conv, two residual blocks, 1x1 conv (NeuRay's)."""

    def __init__(self, in_dim: int, dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(in_dim, dim, 3, 1, 1), nn.ReLU(inplace=True),
                                 ResidualBlock(dim, dim), ResidualBlock(dim, dim), nn.Conv2d(dim, dim, 1))

    def forward(self, image_features: Tensor, initial: Tensor) -> Tensor:
        if initial.shape[-2:] != image_features.shape[-2:]:
            initial = F.interpolate(initial, size=image_features.shape[-2:], mode="bilinear", align_corners=False)
        return self.net(torch.cat([image_features, initial], 1))


def _mlp(dim: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, 32), nn.ELU(), nn.Linear(32, 32), nn.ELU(), nn.Linear(32, out))


class VisibilityDecoder(nn.Module):
    """A two-component mixture of logistics along a source ray from G at a projection (NeuRay's ``dist_decoder`` with
    ``use_vis``): means ``mu >= 0``, inverse scales ``s >= 0.05``, a mixture weight ``a`` and an occlusion ceiling
    ``v``; ``CDF_k(t) = v * sigmoid(2 s_k (t - mu_k))`` (= ``v * (1 + tanh(s_k (t - mu_k))) / 2``)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.mean, self.scale, self.mix, self.ceiling = _mlp(dim, 2), _mlp(dim, 2), _mlp(dim, 1), _mlp(dim, 1)

    def forward(self, g: Tensor, t_low: Tensor, t_high: Tensor) -> tuple[Tensor, Tensor]:
        """``g`` ``[..., dim]``, the sample interval ``[t_low, t_high]`` ``[...]`` in the source ray's normalised
        inverse depth -> (``vis``, ``hit``) ``[...]``: probabilities that the source ray is not stopped before
        ``t_low``, and that it stops within the interval."""
        mean, scale = F.softplus(self.mean(g)), F.softplus(self.scale(g)) + 0.05
        mix, ceiling = torch.sigmoid(self.mix(g)), torch.sigmoid(self.ceiling(g))
        weights = torch.cat([mix, 1.0 - mix], -1)

        def cdf(t: Tensor) -> Tensor:
            return (weights * ceiling * torch.sigmoid(2.0 * scale * (t[..., None] - mean))).sum(-1)

        low = cdf(t_low)
        return 1.0 - low, cdf(t_high) - low
