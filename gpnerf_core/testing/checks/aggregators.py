"""Checks of field aggregators (attention over views per sample) and ray aggregators (attention along each ray)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gpnerf_core.testing.checks.common import (
    Outputs,
    Subject,
    call,
    check_build,
    check_round_trip,
    expect,
    expect_finite,
    expect_gradients,
    expect_modes,
    expect_sums_to_one,
    expect_tensor,
    shape,
    total,
)
from gpnerf_core.testing.inputs import AGGREGATOR_CASES, RAY_IN_DIM, projected, tokens
from gpnerf_core.types import FieldBlockOutput, ProjectedFeatures, RayBlockOutput, RayReadout


def sizes(component: nn.Module, names: tuple[str, ...]) -> dict[str, int]:
    values = call(f"reading {', '.join(names)}", lambda: {name: getattr(component, name) for name in names})
    for name, value in values.items():
        expect(isinstance(value, int) and value > 0, f"{name} is {value!r}, expected a positive int")
    return values


def run_field(field: nn.Module, features: ProjectedFeatures, samples, rays) -> Outputs:
    """``begin`` then every block; returns the tokens and each block's view attention, shapes checked."""
    r, s, v, _ = features.rgb_features.shape
    size = sizes(field, ("width", "attention_channels", "num_blocks"))
    what = f"begin(rgb_features {shape(features.rgb_features)})"
    begun = call(what, field.begin, features, samples, rays)
    expect(isinstance(begun, tuple) and len(begun) == 2,
           f"{what} returned {type(begun).__name__}, expected (tokens, context)")
    x, context = begun
    expect_tensor(x, f"{what} tokens", [r, s, size["width"]], torch.float32)
    outputs = {"begin tokens": x}
    for index in range(size["num_blocks"]):
        what = f"block({index}, tokens {shape(x)})"
        out = call(what, field.block, index, x, context)
        expect(isinstance(out, FieldBlockOutput), f"{what} returned {type(out).__name__}, expected FieldBlockOutput")
        x = expect_tensor(out.tokens, f"{what}.tokens", [r, s, size["width"]], torch.float32)
        outputs[f"block {index} view_attention"] = expect_tensor(
            out.view_attention, f"{what}.view_attention", [r, s, v, size["attention_channels"]], torch.float32)
    outputs["tokens"] = x
    return outputs


def run_ray(ray: nn.Module, x: Tensor) -> Outputs:
    """Every block then ``readout``; returns tokens, each block's ray attention, rgb and weights, shapes checked."""
    r, s, d = x.shape
    size = sizes(ray, ("num_heads", "num_blocks"))
    outputs: Outputs = {}
    last = None
    for index in range(size["num_blocks"]):
        what = f"block({index}, tokens {shape(x)})"
        last = call(what, ray.block, index, x)
        expect(isinstance(last, RayBlockOutput), f"{what} returned {type(last).__name__}, expected RayBlockOutput")
        x = expect_tensor(last.tokens, f"{what}.tokens", [r, s, d], torch.float32)
        outputs[f"block {index} ray_attention"] = expect_tensor(
            last.ray_attention, f"{what}.ray_attention", [r, size["num_heads"], s, s], torch.float32)
    what = f"readout(tokens {shape(x)})"
    readout = call(what, ray.readout, x, last)
    expect(isinstance(readout, RayReadout), f"{what} returned {type(readout).__name__}, expected RayReadout")
    outputs["tokens"] = x
    outputs["rgb"] = expect_tensor(readout.rgb, f"{what}.rgb", [r, 3], torch.float32)
    outputs["weights"] = expect_tensor(readout.weights, f"{what}.weights", [r, s], torch.float32)
    return outputs


def check_field_properties(subject: Subject) -> None:
    sizes(subject.build(), ("width", "attention_channels", "num_blocks"))


def check_ray_properties(subject: Subject) -> None:
    """Positive sizes, and as many blocks as the pipeline asked for (the field aggregator's count)."""
    size = sizes(subject.build(num_blocks=3), ("num_heads", "num_blocks"))
    expect(size["num_blocks"] == 3, f"num_blocks is {size['num_blocks']} for a ray aggregator built with num_blocks=3")


def check_field_shapes(subject: Subject) -> None:
    """Tokens ``[R, S, width]`` and view attention ``[R, S, V, attention_channels]`` for several R, S, V."""
    field = subject.build().eval()
    for case in AGGREGATOR_CASES:
        with torch.no_grad():
            run_field(field, *projected(*case))


def check_ray_shapes(subject: Subject) -> None:
    """Tokens ``[R, S, D]``, ray attention ``[R, H, S, S]``, rgb ``[R, 3]`` and weights ``[R, S]``."""
    ray = subject.build().eval()
    for r, s, _ in AGGREGATOR_CASES:
        with torch.no_grad():
            run_ray(ray, tokens(r, s))


def check_view_attention(subject: Subject) -> None:
    """In eval mode the view attention is a softmax over the V views: >= 0, summing to 1 for every seen sample."""
    field = subject.build().eval()
    for case in AGGREGATOR_CASES:
        features, samples, rays = projected(*case)
        seen = features.visible.any(dim=-1)[..., None]  # [R, S, 1]: the sum over V keeps the channel axis
        with torch.no_grad():
            outputs = run_field(field, features, samples, rays)
        for name, attention in outputs.items():
            if name.endswith("view_attention"):
                channels = attention.shape[-1]
                expect_sums_to_one(attention, 2, f"{name} (softmax over views V)", seen.expand(-1, -1, channels))


def check_ray_attention(subject: Subject) -> None:
    """In eval mode every row of the ray attention is a softmax over the S samples."""
    ray = subject.build().eval()
    for r, s, _ in AGGREGATOR_CASES:
        with torch.no_grad():
            outputs = run_ray(ray, tokens(r, s))
        for name, attention in outputs.items():
            if name.endswith("ray_attention"):
                expect_sums_to_one(attention, -1, f"{name} rows (softmax over samples S)")


def check_readout(subject: Subject) -> None:
    """Readout weights are >= 0 and sum to 1 along each ray, in train and eval mode."""
    ray = subject.build()
    for mode in ("train", "eval"):
        ray.train(mode == "train")
        for r, s, _ in AGGREGATOR_CASES:
            with torch.no_grad():
                weights = run_ray(ray, tokens(r, s))["weights"]
            expect_sums_to_one(weights, -1, "readout weights", when=f"in {mode} mode")


def check_field_gradients(subject: Subject) -> None:
    field = subject.build().train()
    features, samples, rays = projected(*AGGREGATOR_CASES[0])
    features.rgb_features.requires_grad_()
    expect_gradients(field, run_field(field, features, samples, rays), {"rgb_features": features.rgb_features})


def check_ray_gradients(subject: Subject) -> None:
    ray = subject.build().train()
    x = tokens(*AGGREGATOR_CASES[0][:2]).requires_grad_()
    expect_gradients(ray, run_ray(ray, x), {"tokens": x})


def check_field_modes(subject: Subject) -> None:
    inputs = projected(*AGGREGATOR_CASES[0])
    expect_modes(subject, lambda field: run_field(field, *inputs))


def check_ray_modes(subject: Subject) -> None:
    x = tokens(*AGGREGATOR_CASES[0][:2])
    expect_modes(subject, lambda ray: run_ray(ray, x))


def check_field_degenerate(subject: Subject) -> None:
    """All-zero features and pose features, a sample no view sees and a ray no view sees: finite outputs."""
    field = subject.build().train()
    features, samples, rays = projected(4, 5, 2, zeros=True)
    outputs = run_field(field, features, samples, rays)
    expect_finite(outputs, "for all-zero features with unseen samples (visible[0, 0] and visible[-1] all False)")
    call("backward of the sum of the outputs", total(outputs).backward)
    expect_finite({f"gradient of {n}": p.grad for n, p in field.named_parameters() if p.grad is not None},
                  "for all-zero features")


def check_ray_degenerate(subject: Subject) -> None:
    """All-zero tokens, and rays of a single sample: finite outputs, weights still summing to 1."""
    ray = subject.build().eval()
    for r, s in ((4, 5), (3, 1)):
        with torch.no_grad():
            outputs = run_ray(ray, torch.zeros(r, s, RAY_IN_DIM))
        when = f"for all-zero tokens [{r}, {s}, {RAY_IN_DIM}]"
        expect_finite(outputs, when)
        expect_sums_to_one(outputs["weights"], -1, "readout weights", when=when)


FIELD_CHECKS = {
    "build": check_build,
    "properties": check_field_properties,
    "output shapes": check_field_shapes,
    "view attention": check_view_attention,
    "gradients": check_field_gradients,
    "train and eval": check_field_modes,
    "degenerate inputs": check_field_degenerate,
    "config round trip": check_round_trip,
}


RAY_CHECKS = {
    "build": check_build,
    "properties": check_ray_properties,
    "output shapes": check_ray_shapes,
    "ray attention": check_ray_attention,
    "readout": check_readout,
    "gradients": check_ray_gradients,
    "train and eval": check_ray_modes,
    "degenerate inputs": check_ray_degenerate,
    "config round trip": check_round_trip,
}
