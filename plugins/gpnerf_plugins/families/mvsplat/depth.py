"""MVSplat's depth predictor (``costvolume/depth_predictor_multiview.py``): per source view a plane-sweep cost volume of
feature correlations with the other views, refined by a 2D U-Net; depth by soft-argmin over the candidates, upsampled
to the image and refined by a second U-Net on the image, the features and the coarse depth; the refined features then
give each pixel's Gaussian parameters and its depth correction and opacity.

All maps here are ``[V, C, h, w]``: the V source views are the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ReferenceFrustum, SourceViews, plane_sweep


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with up to 8 groups that divide ``channels``."""
    groups = max(g for g in (8, 4, 2, 1) if channels % g == 0)
    return nn.GroupNorm(groups, channels)


class ResidualBlock(nn.Module):
    """LDM's ``ResBlock`` without the time embedding: (GroupNorm, SiLU, 3x3 conv) twice, added to the input."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(group_norm(channels), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1),
                                  group_norm(channels), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


class UNet(nn.Module):
    """A 2D U-Net of ``levels`` resolutions at ``channels`` each (LDM's ``UNetModel`` as MVSplat configures it:
    ``channel_mult`` all 1, one residual block per level, no attention): a block then a stride-2 convolution down each
    level, a middle block, and up each level the skip concatenated, a 1x1 projection, a block and an upsampling."""

    def __init__(self, channels: int, levels: int) -> None:
        super().__init__()
        self.down = nn.ModuleList(ResidualBlock(channels) for _ in range(levels - 1))
        self.pool = nn.ModuleList(nn.Conv2d(channels, channels, 3, stride=2, padding=1) for _ in range(levels - 1))
        self.middle = ResidualBlock(channels)
        self.join = nn.ModuleList(nn.Conv2d(2 * channels, channels, 1) for _ in range(levels - 1))
        self.up = nn.ModuleList(ResidualBlock(channels) for _ in range(levels - 1))
        self.out = nn.Sequential(group_norm(channels), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1))

    def forward(self, x: Tensor) -> Tensor:
        skips = []
        for block, pool in zip(self.down, self.pool):
            x = block(x)
            skips.append(x)
            x = pool(x)
        x = self.middle(x)
        for join, block in zip(self.join, self.up):
            skip = skips.pop()
            x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = block(join(torch.cat([x, skip], dim=1)))
        return self.out(x)


@dataclass(frozen=True)
class DepthOutput:
    """What the depth predictor gives per source pixel (full resolution H x W).

    Attributes:
        depth: ``[V, H, W]`` camera depth of each pixel's Gaussian, metres (within [near, far]).
        opacity: ``[V, H, W]`` in (0, 1).
        raw: ``[V, R, H, W]`` the Gaussian head's raw parameters (offsets, scales, rotation, colour, extras).
        confidence: ``[V, H, W]`` the cost volume's peak probability (MVSplat's ``pdf_max``), upsampled.
    """

    depth: Tensor
    opacity: Tensor
    raw: Tensor
    confidence: Tensor


def candidate_depths(near: float, far: float, count: int, like: Tensor) -> Tensor:
    """``[D]`` depths uniform in inverse depth from ``near`` to ``far`` (ascending depth): MVSplat's candidates, the
    planes of ``correlation_volume``'s frustums (``ReferenceFrustum.depths`` with ``inverse_depth``)."""
    steps = torch.linspace(0.0, 1.0, int(count), dtype=like.dtype, device=like.device)
    return 1.0 / (1.0 / near * (1.0 - steps) + 1.0 / far * steps)


def correlation_volume(features: Tensor, sources: SourceViews, near: float, far: float, count: int) -> Tensor:
    """``[V, D, h, w]``: for each view, the dot product (over C, / sqrt C) of its features with every other view's
    warped onto its D fronto-parallel planes (``gpnerf_core.plane_sweep``, zero where a plane point falls outside a
    view), averaged over the other views. A single view has nothing to match: zeros (the depth then comes from its own
    features alone, as MVSplat's ``wo_cost_volume`` ablation)."""
    views, channels, rows, cols = features.shape
    if views == 1:
        return features.new_zeros(1, int(count), rows, cols)
    volumes = []
    for reference in range(views):
        frustum = ReferenceFrustum(sources.intrinsics[reference], sources.c2w[reference], sources.image_size,
                                   (rows, cols), float(near), float(far), int(count), inverse_depth=True)
        others = [v for v in range(views) if v != reference]
        sweep = plane_sweep(frustum, sources.intrinsics[others], sources.c2w[others])
        warped = sweep.warp(features[others])  # [V - 1, C, D, h, w]
        correlation = (features[reference][None, :, None] * warped).sum(dim=1) / channels**0.5
        volumes.append(correlation.mean(dim=0))
    return torch.stack(volumes)


class DepthPredictor(nn.Module):
    """MVSplat's ``DepthPredictorMultiView`` (the module docstring), with ``raw_channels`` Gaussian parameters per
    pixel.

    Args:
        feature_dim: C of the transformer's (and the CNN's) 1/4 maps.
        candidates: D depth candidates.
        cost_dim, depth_dim: widths of the cost-volume and depth-refinement U-Nets; levels: their resolutions.
        raw_channels: the Gaussian head's outputs per pixel (2 offsets, 3 scales, 4 rotation, colour, extras).
        upscale: the maps' stride (4).
    """

    def __init__(self, *, feature_dim: int, candidates: int, cost_dim: int, depth_dim: int, levels: int,
                 raw_channels: int, upscale: int = 4) -> None:
        super().__init__()
        self.candidates, self.upscale = candidates, upscale
        volume_in = candidates + feature_dim
        self.cost_refine = nn.Sequential(nn.Conv2d(volume_in, cost_dim, 3, padding=1), group_norm(cost_dim), nn.GELU(),
                                         UNet(cost_dim, levels), nn.Conv2d(cost_dim, candidates, 3, padding=1))
        self.cost_residual = nn.Conv2d(volume_in, candidates, 1)
        self.depth_head = nn.Sequential(nn.Conv2d(candidates, 2 * candidates, 3, padding=1), nn.GELU(),
                                        nn.Conv2d(2 * candidates, candidates, 3, padding=1))
        self.upsampler = nn.Sequential(nn.Conv2d(2 * feature_dim, feature_dim, 3, padding=1),
                                       nn.Upsample(scale_factor=upscale, mode="bilinear", align_corners=True),
                                       nn.GELU())
        self.project = nn.Conv2d(feature_dim, depth_dim, 3, padding=1)
        self.depth_refine = nn.Sequential(nn.Conv2d(3 + depth_dim + 2, depth_dim, 3, padding=1), group_norm(depth_dim),
                                          nn.GELU(), UNet(depth_dim, levels))
        gaussian_in = depth_dim + 3 + feature_dim
        self.to_gaussians = nn.Sequential(nn.Conv2d(gaussian_in, 2 * raw_channels, 3, padding=1), nn.GELU(),
                                          nn.Conv2d(2 * raw_channels, raw_channels, 3, padding=1))
        self.to_disparity = nn.Sequential(nn.Conv2d(depth_dim, 2 * depth_dim, 3, padding=1), nn.GELU(),
                                          nn.Conv2d(2 * depth_dim, 2, 3, padding=1))

    def forward(self, features: Tensor, cnn_features: Tensor, sources: SourceViews, near: float,
                far: float) -> DepthOutput:
        """``features`` (after the transformer) and ``cnn_features`` (before it): ``[V, C, h, w]`` at 1/4 of the
        source images ``sources.rgb`` ``[V, 3, H, W]``."""
        depths = candidate_depths(near, far, self.candidates, features)
        disparities = (1.0 / depths)[None, :, None, None]  # [1, D, 1, 1]
        volume = torch.cat([correlation_volume(features, sources, near, far, self.candidates), features], dim=1)
        refined = self.cost_refine(volume) + self.cost_residual(volume)
        pdf = torch.softmax(self.depth_head(refined), dim=1)  # [V, D, h, w]
        coarse = (disparities * pdf).sum(dim=1, keepdim=True)
        size = tuple(sources.rgb.shape[-2:])
        confidence = F.interpolate(pdf.max(dim=1, keepdim=True).values, size=size, mode="nearest")
        full = F.interpolate(coarse, size=size, mode="bilinear", align_corners=True)

        upsampled = self.upsampler(torch.cat([features, cnn_features], dim=1))
        refine = self.depth_refine(torch.cat([sources.rgb, self.project(upsampled), full, confidence], dim=1))
        raw = self.to_gaussians(torch.cat([refine, sources.rgb, upsampled], dim=1))
        delta, density = self.to_disparity(refine).unbind(dim=1)
        disparity = (full[:, 0] + delta).clamp(1.0 / far, 1.0 / near)
        return DepthOutput(depth=1.0 / disparity, opacity=torch.sigmoid(density), raw=raw,
                           confidence=confidence[:, 0])
