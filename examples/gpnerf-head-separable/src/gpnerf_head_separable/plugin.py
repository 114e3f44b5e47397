"""The plugin module the ``gpnerf`` entry point names: hook implementations only."""

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_head_separable.head import SeparableHead, SeparableHeadConfig
from gpnerf_head_separable.loss import DiceLossConfig, DiceLossSet


@hookimpl
def gpnerf_register_heads() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "separable",
            SeparableHead,
            SeparableHeadConfig,
            "light context head: depthwise-separable convolutions over the semantic levels, coarse to fine",
        )
    ]


@hookimpl
def gpnerf_register_losses() -> list[ComponentSpec]:
    return [
        ComponentSpec("dice", DiceLossSet, DiceLossConfig, "a loss set (default dgs) + soft Dice on the logits")
    ]
