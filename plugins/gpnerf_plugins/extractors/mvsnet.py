"""The ``mvsnet`` feature extractor: MVSNeRF's FeatureNet (MVSNet's 2D encoder), 32 channels at 1/4, radiance only.

Three conv blocks on ImageNet-normalised images: 3->8->8 at full resolution, 8->16 (5x5, stride 2)->16->16 at 1/2,
16->32 (5x5, stride 2)->32->32 at 1/4, then a 1x1 conv 32->32. Each conv is followed by InPlaceABN in the official code
(``apchenstu/mvsnerf``, ``models.py``: batch norm and a leaky ReLU of slope 0.01, the package's default); here it is
``BatchNorm2d`` then ``LeakyReLU(0.01)``: the same function and parameters, without the in-place memory saving.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from gpnerf_core import ConfigError, FeatureExtractor, FeatureMaps

_STRIDE = 4  # the map's stride: image sides must be multiples of it for the map's cells to tile the image
_CHANNELS = 32
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class MVSNetFeaturesConfig:
    """Options of the ``mvsnet`` extractor (MVSNeRF's FeatureNet has none: 32 channels at 1/4)."""

    name: str = "mvsnet"
    """Registry name of the extractor."""


def conv_bn_act(in_channels: int, out_channels: int, kernel: int = 3, stride: int = 1) -> nn.Sequential:
    """Conv (no bias) + BatchNorm + LeakyReLU(0.01): MVSNeRF's ``ConvBnReLU`` with InPlaceABN unrolled."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(0.01),
    )


def imagenet_normalised(images: Tensor) -> Tensor:
    """``[N, 3, H, W]`` images in [0, 1] normalised by the ImageNet mean and standard deviation (MVSNeRF's input)."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=images.dtype, device=images.device)[:, None, None]
    std = torch.tensor(IMAGENET_STD, dtype=images.dtype, device=images.device)[:, None, None]
    return (images - mean) / std


class MVSNetFeatures(FeatureExtractor):
    """MVSNeRF's FeatureNet: ``[N, 3, H, W]`` in [0, 1] -> ``FeatureMaps(radiance=[N, 32, H/4, W/4], semantic=None)``.

    H and W must be multiples of 4 (the map then tiles the image exactly); other sizes are refused.
    """

    def __init__(self) -> None:
        super().__init__()
        self.conv0 = nn.Sequential(conv_bn_act(3, 8), conv_bn_act(8, 8))
        self.conv1 = nn.Sequential(conv_bn_act(8, 16, 5, 2), conv_bn_act(16, 16), conv_bn_act(16, 16))
        self.conv2 = nn.Sequential(conv_bn_act(16, 32, 5, 2), conv_bn_act(32, 32), conv_bn_act(32, 32))
        self.toplayer = nn.Conv2d(32, _CHANNELS, 1)

    @property
    def radiance_dim(self) -> int:
        return _CHANNELS

    def check_image_size(self, height: int, width: int) -> None:
        """H and W multiples of 4."""
        if height % _STRIDE or width % _STRIDE or min(height, width) < _STRIDE:
            raise ConfigError(
                f"image size {height}x{width} (HxW) is not a multiple of {_STRIDE}, which the mvsnet extractor needs "
                f"(its map has 1/{_STRIDE} of the image's cells); resize or crop the images"
            )

    def forward(self, images: Tensor) -> FeatureMaps:
        """Encode ``[N, 3, H, W]`` images in [0, 1] (H, W multiples of 4)."""
        if images.dim() != 4 or images.shape[1] != 3:
            raise ConfigError(f"feature extractor input has shape {tuple(images.shape)}; expected [N, 3, H, W]")
        self.check_image_size(int(images.shape[-2]), int(images.shape[-1]))
        x = self.conv2(self.conv1(self.conv0(imagenet_normalised(images))))
        return FeatureMaps(radiance=self.toplayer(x), semantic=None)
