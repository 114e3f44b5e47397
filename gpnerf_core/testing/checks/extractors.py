"""Checks of feature extractors: ``extractor(images [N, 3, H, W]) -> FeatureMaps(radiance, semantic)``."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gpnerf_core.errors import GpnerfError
from gpnerf_core.testing.checks.common import (
    CheckFailed,
    Outputs,
    Subject,
    call,
    check_build,
    check_round_trip,
    expect,
    expect_finite,
    expect_gradients,
    expect_modes,
    expect_tensor,
    shape,
)
from gpnerf_core.testing.inputs import EXTRACTOR_OTHER_SIZES, EXTRACTOR_SIZES, images
from gpnerf_core.types import FeatureMaps


def widths(extractor: nn.Module) -> tuple[int, int, int]:
    return call("reading radiance_dim, semantic_dim and semantic_levels",
                lambda: (extractor.radiance_dim, extractor.semantic_dim, extractor.semantic_levels))


def maps(extractor: nn.Module, batch: Tensor) -> Outputs:
    """The extractor's maps, checked against its declared widths: ``{"radiance": ..., "semantic": ...}``."""
    what = f"extractor(images {shape(batch)})"
    output = call(what, extractor, batch)
    expect(isinstance(output, FeatureMaps), f"{what} returned {type(output).__name__}, expected FeatureMaps")
    radiance_dim, semantic_dim, _ = widths(extractor)
    n = int(batch.shape[0])
    outputs = {"radiance": expect_tensor(output.radiance, f"{what}.radiance")}
    if semantic_dim == 0:
        expect(output.semantic is None, f"{what}.semantic is {shape(output.semantic)} but semantic_dim is 0")
    else:
        outputs["semantic"] = expect_tensor(output.semantic, f"{what}.semantic")
    declared = {"radiance": radiance_dim, "semantic": semantic_dim}
    for name, tensor in outputs.items():
        ok = tensor.dim() == 4 and list(tensor.shape[:2]) == [n, declared[name]] and min(tensor.shape[2:]) >= 1
        expect(ok, f"{name} map {shape(tensor)} for images {shape(batch)}, expected [{n}, {declared[name]}, h, w] "
                   f"({name}_dim={declared[name]})")
        expect(tensor.dtype == torch.float32, f"{name} map {shape(tensor)} has dtype {tensor.dtype}, expected float32")
    return outputs


def check_properties(subject: Subject) -> None:
    """Positive radiance width; semantic width 0 exactly when there are no levels, else a multiple of the levels."""
    radiance_dim, semantic_dim, levels = widths(subject.build())
    expect(isinstance(radiance_dim, int) and radiance_dim > 0,
           f"radiance_dim is {radiance_dim!r}, expected a positive int")
    expect(isinstance(semantic_dim, int) and semantic_dim >= 0,
           f"semantic_dim is {semantic_dim!r}, expected an int >= 0")
    expect(isinstance(levels, int) and levels >= 0, f"semantic_levels is {levels!r}, expected an int >= 0")
    expect((semantic_dim == 0) == (levels == 0), f"semantic_dim={semantic_dim} with semantic_levels={levels}: both or "
                                                 f"neither must be 0")
    expect(levels == 0 or semantic_dim % levels == 0,
           f"semantic_dim={semantic_dim} is not divisible into semantic_levels={levels} equal blocks")


def check_output_shapes(subject: Subject) -> None:
    """Maps of ``[N, radiance_dim, h, w]`` and ``[N, semantic_dim, h, w]`` (or None) for image sizes divisible by 16."""
    extractor = subject.build().eval()
    for n, height, width in EXTRACTOR_SIZES:
        with torch.no_grad():
            maps(extractor, images(n, height, width))


def check_other_sizes(subject: Subject) -> None:
    """Sizes not divisible by 16 are either encoded correctly or refused with a ``GpnerfError`` naming the size."""
    extractor = subject.build().eval()
    for n, height, width in EXTRACTOR_OTHER_SIZES:
        batch = images(n, height, width)
        try:
            with torch.no_grad():
                maps(extractor, batch)
        except CheckFailed as failure:
            cause = failure.__cause__
            if isinstance(cause, GpnerfError):
                continue  # refused in one clear line: allowed
            raise CheckFailed(f"{failure}; refuse image sizes you cannot encode with a gpnerf_core.errors.ConfigError "
                              f"naming the size") from None


def check_gradients(subject: Subject) -> None:
    extractor = subject.build().train()
    expect_gradients(extractor, maps(extractor, images(2, 32, 48)))


def check_modes(subject: Subject) -> None:
    batch = images(2, 32, 48)
    expect_modes(subject, lambda extractor: maps(extractor, batch))


def check_degenerate(subject: Subject) -> None:
    """Black and white images give finite maps."""
    extractor = subject.build().eval()
    for fill in (0.0, 1.0):
        with torch.no_grad():
            expect_finite(maps(extractor, torch.full((1, 3, 32, 48), fill)), f"for an image of constant {fill:g}")


CHECKS = {
    "build": check_build,
    "properties": check_properties,
    "output shapes": check_output_shapes,
    "other image sizes": check_other_sizes,
    "gradients": check_gradients,
    "train and eval": check_modes,
    "degenerate inputs": check_degenerate,
    "config round trip": check_round_trip,
}
