"""Checks of feature providers: ``channels`` and ``stride`` positive ints, ``fingerprint()`` a stable non-empty str,
``compute(scene, frames, images [B, 3, H, W]) -> [B, C, h, w]`` float32, finite, deterministic, at the frame size over
``stride`` for several sizes; ``encode_text`` gives ``[N, C]`` or refuses with a ``ConfigError``. A provider that
refuses to build here with a gpnerf-core error (a weights file, a files layout or a package it needs is missing) is
skipped: its refusal is its test."""

from __future__ import annotations

from typing import Any

import torch

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.testing.checks.common import (
    CheckFailed, CheckSkipped, Subject, call, expect, expect_finite, expect_tensor, round_tripped, shape,
)
from gpnerf_core.testing.inputs import images

SIZES = ((32, 48), (40, 56))
"""Frame sizes the kit computes at (a multiple of 8 and 16; XFeat resizes the second to multiples of 32)."""


def built(subject: Subject) -> Any:
    """The provider, or a skip when it refuses to build here with one of gpnerf-core's errors (what it needs is not
    here: a weights file, a files layout, a package)."""
    try:
        return subject.build()
    except CheckFailed as failure:
        if isinstance(failure.__cause__, GpnerfError):
            raise CheckSkipped(f"it does not build here without what it reads ({failure})") from None
        raise


def computed(provider: Any, frames: list[int], height: int, width: int, seed: int = 0) -> torch.Tensor:
    """``compute`` on kit images, checked against the interface."""
    given = images(len(frames), height, width, seed=seed)
    what = f"compute('kit', {frames}, images {shape(given)})"
    out = call(what, provider.compute, "kit", frames, given)
    h, w = provider.feature_size(height, width)
    out = expect_tensor(out, what, [len(frames), int(provider.channels), h, w], torch.float32)
    expect_finite({what: out}, "")
    return out


def check_properties(subject: Subject) -> None:
    """``channels`` and ``stride`` positive ints; ``text_encoder`` a bool; ``fingerprint()`` a non-empty str, the
    same twice and for a second build of the same config."""
    provider = built(subject)
    for name in ("channels", "stride"):
        value = getattr(provider, name, None)
        expect(isinstance(value, int) and not isinstance(value, bool) and value >= 1,
               f"{name} is {value!r}, expected a positive int")
    expect(isinstance(provider.text_encoder, bool), f"text_encoder is {provider.text_encoder!r}, expected a bool")
    first = call("fingerprint()", provider.fingerprint)
    expect(isinstance(first, str) and bool(first), f"fingerprint() is {first!r}, expected a non-empty str")
    expect(call("fingerprint()", provider.fingerprint) == first, "fingerprint() differs between two calls")
    expect(built(subject).fingerprint() == first, "fingerprint() differs between two builds of the same config")


def check_output_shapes(subject: Subject) -> None:
    """``[B, C, h, w]`` float32 finite maps at the kit's frame sizes, one frame and several."""
    provider = built(subject)
    for height, width in SIZES:
        computed(provider, [0, 1], height, width)
    computed(provider, [2], *SIZES[0])


def check_determinism(subject: Subject) -> None:
    """The same frames give the same features, whatever torch's global random state, alone or in a batch."""
    provider = built(subject)
    torch.manual_seed(1)
    first = computed(provider, [0, 1], *SIZES[0])
    torch.manual_seed(2)
    second = computed(provider, [0, 1], *SIZES[0])
    expect(torch.equal(first, second), "compute differs between two calls on the same frames")
    alone = call("compute of one frame", provider.compute, "kit", [0], images(2, *SIZES[0])[:1])
    expect(torch.allclose(alone, first[:1], atol=1e-5), "a frame's features differ alone and in a batch (max "
                                                        f"{float((alone - first[:1]).abs().max()):.3g})")


def check_text(subject: Subject) -> None:
    """With ``text_encoder``: ``encode_text`` gives ``[N, C]`` float32 finite; without: a ``ConfigError``."""
    provider = built(subject)
    if not provider.text_encoder:
        try:
            provider.encode_text(["a chair"])
        except ConfigError:
            return
        except Exception as exc:
            raise CheckFailed(f"encode_text without a text encoder raised {type(exc).__name__}, expected a "
                              "ConfigError naming the provider") from None
        raise CheckFailed("encode_text without a text encoder returned instead of raising a ConfigError")
    raise CheckSkipped("its texts are its own (checked by its tests)")


def check_round_trip(subject: Subject) -> None:
    """The config survives Hydra's round trip; where the provider builds here, it builds from it with the same
    fingerprint."""
    node = round_tripped(subject)
    try:
        direct = built(subject)
    except CheckSkipped:
        return
    expect(subject.build(node).fingerprint() == direct.fingerprint(),
           "built from the round-tripped config, the fingerprint differs from the config's own")


CHECKS = {
    "properties": check_properties,
    "output shapes": check_output_shapes,
    "determinism": check_determinism,
    "text encoder": check_text,
    "config round trip": check_round_trip,
}
