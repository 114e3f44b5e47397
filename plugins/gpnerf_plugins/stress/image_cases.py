"""Stress cases on what the source images look like: sensor noise, blur, JPEG artefacts, exposure."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import torch
from PIL import Image

from gpnerf_core import SourceViews, StressCase


class GaussianNoise(StressCase):
    name = "gaussian_noise"
    description = "additive Gaussian noise on the source images, sigma 0.02, 0.05, 0.1 (of the [0, 1] range)"
    axis = "noise sigma (fraction of the intensity range)"
    levels = (0.02, 0.05, 0.1)
    quick_levels = (0.1,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        noise = torch.randn(sources.rgb.shape, generator=generator).to(sources.rgb) * level
        return replace(sources, rgb=(sources.rgb + noise).clamp(0.0, 1.0))


def gaussian_kernel(sigma: float) -> torch.Tensor:
    """A normalised 1D Gaussian kernel reaching 3 sigma each side."""
    radius = max(1, int(round(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    return kernel / kernel.sum()


def blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[V, C, H, W]`` with reflected borders."""
    kernel = gaussian_kernel(sigma).to(images)
    radius = kernel.numel() // 2
    channels = images.shape[1]
    out = torch.nn.functional.pad(images, (radius, radius, 0, 0), mode="reflect")
    out = torch.nn.functional.conv2d(out, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    out = torch.nn.functional.pad(out, (0, 0, radius, radius), mode="reflect")
    return torch.nn.functional.conv2d(out, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)


class Blur(StressCase):
    name = "blur"
    description = "Gaussian blur of the source images, sigma 0.5, 1, 2 pixels"
    axis = "blur sigma (pixels)"
    levels = (0.5, 1.0, 2.0)
    quick_levels = (2.0,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        return replace(sources, rgb=blur(sources.rgb, level).clamp(0.0, 1.0))


def jpeg_roundtrip(images: torch.Tensor, quality: int) -> torch.Tensor:
    """Encode each ``[3, H, W]`` image of ``[V, 3, H, W]`` as baseline JPEG at ``quality`` and decode it."""
    out = []
    for image in images:
        array = (image.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        buffer = io.BytesIO()
        Image.fromarray(array).save(buffer, format="JPEG", quality=int(quality))
        decoded = np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB"))
        out.append(torch.from_numpy(decoded.copy()).permute(2, 0, 1))
    return (torch.stack(out).float() / 255.0).to(images)


class Jpeg(StressCase):
    name = "jpeg"
    description = "JPEG compression of the source images at quality 50, 20, 8"
    axis = "JPEG quality (lower is more severe)"
    levels = (50.0, 20.0, 8.0)
    quick_levels = (8.0,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        return replace(sources, rgb=jpeg_roundtrip(sources.rgb, int(level)))


class Exposure(StressCase):
    name = "exposure"
    description = "over-exposed source images: intensities x 2^EV for EV 0.5, 1, 2, clipped at 1 (saturation)"
    axis = "over-exposure (EV stops)"
    levels = (0.5, 1.0, 2.0)
    quick_levels = (2.0,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        return replace(sources, rgb=(sources.rgb * 2.0 ** level).clamp(0.0, 1.0))
