"""Checks of perception heads: ``head(features [N, in_dim, h, w], output_size) -> HeadOutput(logits)``.

The logits must be ``[N, K, *output_size]`` with ``K = num_outputs``, whatever the map size.
"""

from __future__ import annotations

import torch
from torch import Tensor

from gpnerf_core.testing.checks.common import (
    CheckFailed,
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
from gpnerf_core.testing.inputs import HEAD_CASES, HEAD_CLASSES, HEAD_IN_DIM, head_features
from gpnerf_core.types import HeadOutput

GRADIENT_CASE = ((2, 7, 9), (37, 45))  # features [2, in_dim, 7, 9] decoded to 37 x 45


def logits(head: torch.nn.Module, features: Tensor, output_size: tuple[int, int]) -> Tensor:
    """The head's logits; a head that raises or returns anything but a ``HeadOutput`` fails the check."""
    what = f"head(features {shape(features)}, output_size {output_size})"
    output = call(what, head, features, output_size)
    expect(isinstance(output, HeadOutput), f"{what} returned {type(output).__name__}, expected HeadOutput")
    return expect_tensor(output.logits, f"{what}.logits")


def outputs(subject: Subject, classes: int) -> int:
    """K for a check: the class count, or at least 2 for an instance head (one slot + "no instance")."""
    return max(classes, 2) if subject.predicts_instances else classes


def check_num_outputs(subject: Subject) -> None:
    """``num_outputs`` reports the K the pipeline asked for (the logits' channels are checked against it)."""
    for classes in sorted({outputs(subject, k) for k in HEAD_CLASSES}):
        head = subject.build(num_outputs=classes)
        reported = call("reading num_outputs", lambda: head.num_outputs)
        expect(reported == classes, f"num_outputs is {reported!r} for a head built with num_outputs={classes}")


def check_output_size(subject: Subject) -> None:
    """Logits are ``[N, K, *output_size]`` for odd map sizes, 1 and 51 classes and sizes no multiple of the map."""
    for batch, classes, size, output_size in HEAD_CASES:
        classes = outputs(subject, classes)
        head = subject.build(num_outputs=classes).eval()
        features = head_features(batch, size)
        with torch.no_grad():
            got = logits(head, features, output_size)
        expected = [batch, classes, *output_size]
        expect(list(got.shape) == expected,
               f"logits {shape(got)}, expected {expected} for features {shape(features)} and output_size {output_size}")


def check_dtype(subject: Subject) -> None:
    """float32 features give float32 logits."""
    head = subject.build().eval()
    with torch.no_grad():
        got = logits(head, head_features(1, (7, 9)), (14, 18))
    expect(got.dtype == torch.float32,
           f"logits {shape(got)} have dtype {got.dtype} for float32 features, expected float32")


def check_gradients(subject: Subject) -> None:
    """A backward of the logits' sum reaches every parameter and the input features."""
    head = subject.build().train()
    (batch, *size), output_size = GRADIENT_CASE
    features = head_features(batch, tuple(size)).requires_grad_()
    expect_gradients(head, {"logits": logits(head, features, output_size)}, {"features": features})


def check_modes(subject: Subject) -> None:
    features = head_features(2, (7, 9))
    expect_modes(subject, lambda head: {"logits": logits(head, features, (37, 45))})


def check_degenerate(subject: Subject) -> None:
    """All-zero and constant features, and a single class, give finite logits and finite gradients."""
    for classes in sorted({outputs(subject, k) for k in (1, 3)}):
        for fill in (0.0, 1.0):
            head = subject.build(num_outputs=classes).train()
            features = torch.full((1, HEAD_IN_DIM, 7, 9), fill, requires_grad=True)
            out = logits(head, features, (14, 18))
            when = f"for features {shape(features)} all {fill:g} and num_outputs={classes}"
            expect_finite({"logits": out}, when)
            call("backward of the logits' sum", out.sum().backward)
            gradients = {f"gradient of {n}": p.grad for n, p in head.named_parameters() if p.grad is not None}
            if features.grad is None:
                raise CheckFailed(f"no gradient reached the input features {when}")
            expect_finite({"gradient of the features": features.grad, **gradients}, when)


CHECKS = {
    "build": check_build,
    "num_outputs": check_num_outputs,
    "output size": check_output_size,
    "dtype": check_dtype,
    "gradients": check_gradients,
    "train and eval": check_modes,
    "degenerate inputs": check_degenerate,
    "config round trip": check_round_trip,
}
