"""Registers the built-in model families, each with the name ``report`` gives its runs (``display_name``)."""

from __future__ import annotations

from typing import Any, Callable, Mapping

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.families.dm_nerf.build import build_dm_nerf
from gpnerf_plugins.families.dm_nerf.config import DMNeRFConfig
from gpnerf_plugins.families.gnt.build import build_gnt
from gpnerf_plugins.families.gnt.config import GNTModelConfig
from gpnerf_plugins.families.mask_rcnn.build import build_mask_rcnn
from gpnerf_plugins.families.mask_rcnn.config import MaskRCNNConfig
from gpnerf_plugins.families.mvsnerf.build import build_mvsnerf
from gpnerf_plugins.families.mvsnerf.config import MVSNeRFConfig
from gpnerf_plugins.families.mvsplat.build import build_mvsplat
from gpnerf_plugins.families.mvsplat.config import MVSplatConfig
from gpnerf_plugins.families.neuray.build import build_neuray, build_semantic_ray
from gpnerf_plugins.families.neuray.config import NeuRayConfig, SemanticRayConfig
from gpnerf_plugins.families.semantic_3dgs.build import build_semantic_3dgs
from gpnerf_plugins.families.semantic_3dgs.config import Semantic3DGSConfig
from gpnerf_plugins.families.semantic_nerf.build import build_semantic_nerf
from gpnerf_plugins.families.semantic_nerf.config import SemanticNeRFConfig


def _head(config: Mapping[str, Any]) -> str | None:
    return (config.get("head") or {}).get("name")


def gp_nerf_name(config: Mapping[str, Any]) -> str:
    """GP-NeRF; its field without the semantic field and head is GNT's."""
    semantic_field = ((config.get("model") or {}).get("semantic_field") or {}).get("enabled", True)
    return "GNT" if _head(config) is None and not semantic_field else "GP-NeRF"


def with_semantic_head(method: str) -> Callable[[Mapping[str, Any]], str]:
    """The name GP-NeRF's Table 1 gives a method it extended with label rendering: ``<method> + semantic head``
    (``<method> + <head> head`` with a ``+head``)."""
    return lambda config: f"{method} + {_head(config) or 'semantic'} head"


def semantic_nerf_name(config: Mapping[str, Any]) -> str:
    """Semantic-NeRF; its hash-grid option (``model.field=grid``) is not the paper's network."""
    return "Semantic-NeRF grid" if (config.get("model") or {}).get("field", "mlp") == "grid" else "Semantic-NeRF"


def mask_rcnn_name(config: Mapping[str, Any]) -> str:
    """Mask R-CNN, or its Swin-T variant (``model.backbone=swin_t``): Table 2's "Mask R-CNN" and "Swin-T" rows."""
    backbone = (config.get("model") or {}).get("backbone", "resnet34")
    return "Mask R-CNN Swin-T (2D)" if backbone == "swin_t" else "Mask R-CNN (2D)"


@hookimpl
def gpnerf_register_models() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "gnt",
            build_gnt,
            GNTModelConfig,
            "GNT view + ray transformers over source views; GP-NeRF's semantic field on their attention, +head decodes",
            display_name=gp_nerf_name,
        ),
        ComponentSpec(
            "mvsnerf",
            build_mvsnerf,
            MVSNeRFConfig,
            "MVSNeRF + semantic head: plane-sweep cost volume, 3D U-Net encoding volume, modulated MLP, label rendering",
            display_name=with_semantic_head("MVSNeRF"),
        ),
        ComponentSpec(
            "mvsplat",
            build_mvsplat,
            MVSplatConfig,
            "MVSplat: feed-forward 3D Gaussians from a cost volume, one per source pixel, rasterized; label rendering or "
            "+head decodes",
            display_name="MVSplat",
        ),
        ComponentSpec(
            "neuray",
            build_neuray,
            NeuRayConfig,
            "NeuRay + semantic head: visibility from source depth, occlusion-aware pooling, label rendering",
            display_name=with_semantic_head("NeuRay"),
        ),
        ComponentSpec(
            "semantic_ray",
            build_semantic_ray,
            SemanticRayConfig,
            "Semantic-Ray: NeuRay + Cross-Reprojection Attention, per-view scores blended and label-rendered",
            display_name="Semantic-Ray",
        ),
        ComponentSpec(
            "semantic_nerf",
            build_semantic_nerf,
            SemanticNeRFConfig,
            "Semantic-NeRF, per scene: positional-encoding MLP with a semantic branch, coarse + fine, label rendering",
            display_name=semantic_nerf_name,
        ),
        ComponentSpec(
            "semantic_3dgs",
            build_semantic_3dgs,
            Semantic3DGSConfig,
            "3D Gaussian splatting per scene with a semantic feature per Gaussian: densified while it trains, "
            "rasterized; a 1x1 decoder or +head",
            display_name="Semantic 3DGS",
        ),
        ComponentSpec(
            "dm_nerf",
            build_dm_nerf,
            DMNeRFConfig,
            "DM-NeRF, per scene: NeRF field + object field on detached features, sigmoid slots, instance AP",
            display_name="DM-NeRF",
        ),
        ComponentSpec(
            "mask_rcnn",
            build_mask_rcnn,
            MaskRCNNConfig,
            "Mask R-CNN, per scene, 2D: segments the real held-out image (ResNet-34 or Swin-T + FPN), instance AP",
            display_name=mask_rcnn_name,
        ),
    ]
