"""Refusing ``mvsplat`` weights of the structure before issue 55 (``MVSplatHooks.check_weights``).

Issue 55 made the family's U-Nets MVSplat's post-norm LDM ``UNetModel`` (input convolution, two residual blocks in
the middle and per level on the way up, upsampling convolutions) and its cross-view attention read the block's input:
weights trained before fit neither the tensors nor the computation, so they are refused in one line (retrain) rather
than as a list of missing tensors.
"""

from __future__ import annotations

from typing import Mapping

from torch import Tensor

from gpnerf_core import DataError, FamilyHooks

OLD_UNET_MARK = ".body."
"""In a key under ``depth.``: the pre-norm residual block before issue 55 (``ResidualBlock.body``), absent since."""


def predates_issue_55(keys: list[str]) -> str | None:
    """The first key of an ``mvsplat`` state dict with the structure before issue 55, or None."""
    return next((key for key in keys if key.startswith("depth.") and OLD_UNET_MARK in key), None)


class MVSplatHooks(FamilyHooks):
    """``mvsplat``'s hooks: weights of the structure before issue 55 are refused (the module docstring)."""

    def check_weights(self, weights: Mapping[str, Tensor], source: str) -> None:
        old = predates_issue_55(list(weights))
        if old is not None:
            raise DataError(f"{source} is an mvsplat model from before issue 55's structure (its tensor {old!r} is the "
                            "old pre-norm U-Net's; the U-Nets and the cross-view attention are MVSplat's since): "
                            "retrain it with this version (python -m gpnerf_core run +experiment=baselines/mvsplat...)")
