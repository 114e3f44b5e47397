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


COST_REFINE_GROUPS = 8
"""GroupNorm groups after the cost volume's input convolution (the official ``nn.GroupNorm(8, channels)``)."""

DEPTH_REFINE_GROUPS = 4
"""GroupNorm groups after the depth refinement's input convolution (the official ``nn.GroupNorm(4, channels)``; 8
before issue 55)."""


def group_norm(channels: int, groups: int = 8) -> nn.GroupNorm:
    """GroupNorm with ``groups`` groups where they divide ``channels`` (the LDM code's ``normalization`` as MVSplat
    calls it: 8, 4 where 8 do not divide), else the largest of 4, 2 or 1 below it that does (for the small widths
    of the tests, which the official never takes)."""
    return nn.GroupNorm(max(g for g in (groups, 4, 2, 1) if g <= groups and channels % g == 0), channels)


class ResidualBlock(nn.Module):
    """LDM's ``ResBlock`` as MVSplat builds it (``postnorm=True``, no time embedding): (3x3 conv, GroupNorm, SiLU)
    twice, the second GroupNorm zero-initialised (so the block starts as its skip path), added to the input or, when
    the width changes, to its 1x1 projection."""

    def __init__(self, channels: int, out_channels: int | None = None) -> None:
        super().__init__()
        out_channels = out_channels or channels
        self.in_layers = nn.Sequential(nn.Conv2d(channels, out_channels, 3, padding=1), group_norm(out_channels),
                                       nn.SiLU())
        final_norm = group_norm(out_channels)
        nn.init.zeros_(final_norm.weight)
        nn.init.zeros_(final_norm.bias)
        self.out_layers = nn.Sequential(nn.Conv2d(out_channels, out_channels, 3, padding=1), final_norm, nn.SiLU())
        self.skip = nn.Identity() if out_channels == channels else nn.Conv2d(channels, out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.skip(x) + self.out_layers(self.in_layers(x))


class UNet(nn.Module):
    """LDM's ``UNetModel`` as MVSplat configures it (``ldm_unet/unet.py``: ``num_res_blocks`` 1, ``channel_mult`` all
    1 over ``levels`` resolutions, no attention, ``postnorm``, ``conv_resample``) at ``channels`` wide: an input 3x3
    convolution; per level a residual block, and a stride-2 3x3 convolution down between levels; two residual blocks
    in the middle; up each level two residual blocks, each on the current map concatenated with the next saved skip
    (2C -> C), then (but at the last level) a nearest 2x upsampling and a 3x3 convolution; an output 3x3 convolution,
    GroupNorm and SiLU. Sides that do not halve evenly are upsampled to the skip's size (the official needs them
    even)."""

    def __init__(self, channels: int, levels: int) -> None:
        super().__init__()
        self.levels = levels
        self.stem = nn.Conv2d(channels, channels, 3, padding=1)
        self.encoder = nn.ModuleList()
        for level in range(levels):
            self.encoder.append(ResidualBlock(channels))
            if level != levels - 1:
                self.encoder.append(nn.Conv2d(channels, channels, 3, stride=2, padding=1))
        self.middle = nn.Sequential(ResidualBlock(channels), ResidualBlock(channels))
        self.decoder = nn.ModuleList(ResidualBlock(2 * channels, channels) for _ in range(2 * levels))
        self.upsample = nn.ModuleList(nn.Conv2d(channels, channels, 3, padding=1) for _ in range(levels - 1))
        self.out = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), group_norm(channels), nn.SiLU())

    def forward(self, x: Tensor) -> Tensor:
        x = self.stem(x)
        skips = [x]
        for module in self.encoder:
            x = module(x)
            skips.append(x)
        x = self.middle(x)
        for index, block in enumerate(self.decoder):
            x = block(torch.cat([x, skips.pop()], dim=1))
            if index % 2 == 1 and index // 2 < self.levels - 1:
                x = F.interpolate(x, size=skips[-1].shape[-2:], mode="nearest")
                x = self.upsample[index // 2](x)
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
    view), averaged over the other views. A single view has nothing to match: zeros, this project's own one-view
    fallback (the same networks, trained on two views, then read the depth from the view's own features and an empty
    volume; the official code has no one-view path, and its ``wo_cost_volume`` ablation is another network without
    the volume's channels)."""
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
        self.cost_refine = nn.Sequential(nn.Conv2d(volume_in, cost_dim, 3, padding=1),
                                         group_norm(cost_dim, COST_REFINE_GROUPS), nn.GELU(),
                                         UNet(cost_dim, levels), nn.Conv2d(cost_dim, candidates, 3, padding=1))
        self.cost_residual = nn.Conv2d(volume_in, candidates, 1)
        self.depth_head = nn.Sequential(nn.Conv2d(candidates, 2 * candidates, 3, padding=1), nn.GELU(),
                                        nn.Conv2d(2 * candidates, candidates, 3, padding=1))
        self.upsampler = nn.Sequential(nn.Conv2d(2 * feature_dim, feature_dim, 3, padding=1),
                                       nn.Upsample(scale_factor=upscale, mode="bilinear", align_corners=True),
                                       nn.GELU())
        self.project = nn.Conv2d(feature_dim, depth_dim, 3, padding=1)
        self.depth_refine = nn.Sequential(nn.Conv2d(3 + depth_dim + 2, depth_dim, 3, padding=1),
                                          group_norm(depth_dim, DEPTH_REFINE_GROUPS), nn.GELU(),
                                          UNet(depth_dim, levels))
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
