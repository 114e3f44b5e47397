"""Registers the built-in loss sets (GP-NeRF's Table 4 rows, the instance set, the label-free set and DM-NeRF's)."""

from __future__ import annotations

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.losses.dm_nerf import DMNeRFLossConfig, DMNeRFLossSet
from gpnerf_plugins.losses.instance import InstanceLossConfig, InstanceLossSet
from gpnerf_plugins.losses.sets import (
    CeLossConfig,
    DgsLossConfig,
    ImageLossConfig,
    ImageLossSet,
    LabelFreeLossConfig,
    LabelFreeLossSet,
    RgbLossConfig,
    SdLossConfig,
    WeightedLossSet,
)


@hookimpl
def gpnerf_register_losses() -> list[ComponentSpec]:
    return [
        ComponentSpec("rgb", WeightedLossSet, RgbLossConfig, "colour only (GNT)"),
        ComponentSpec("ce", WeightedLossSet, CeLossConfig, "colour + semantic cross-entropy"),
        ComponentSpec("sd", WeightedLossSet, SdLossConfig, "colour + cross-entropy + 2D semantic distillation"),
        ComponentSpec("dgs", WeightedLossSet, DgsLossConfig, "colour + cross-entropy + 2D and depth-guided distill."),
        ComponentSpec("image", ImageLossSet, ImageLossConfig,
                      "colour MSE + D-SSIM on whole images + cross-entropy (Gaussian splatting: MVSplat's)"),
        ComponentSpec("instance", InstanceLossSet, InstanceLossConfig, "colour + Hungarian instance loss + 2D distill"),
        ComponentSpec(
            "label_free", LabelFreeLossSet, LabelFreeLossConfig, "colour + 2D and depth-guided distill., no labels"
        ),
        ComponentSpec("dm_nerf", DMNeRFLossSet, DMNeRFLossConfig,
                      "DM-NeRF: colour + Hungarian object loss (sigmoid slots) + 3D emptiness penalty, per pass"),
    ]
