"""Checks of loss sets: ``loss(LossInputs | ImageLossInputs) -> {term: weighted scalar}``, with ``needs_*`` flags that
tell the truth."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from gpnerf_core.testing.checks.common import (
    CheckFailed,
    Outputs,
    Subject,
    call,
    check_build,
    check_round_trip,
    expect,
    expect_finite,
    expect_modes,
    shape,
)
from gpnerf_core.testing.inputs import loss_inputs, loss_leaves
from gpnerf_core.types import ImageLossInputs, LossInputs

SEMANTIC_LEAVES = ("logits", "semantic", "sample_semantic", "scores")


def flags(loss: Any) -> tuple[bool, bool]:
    semantics, samples = call("reading the needs_* flags", lambda: (loss.needs_semantics, loss.needs_sample_semantics))
    for name, value in (("needs_semantics", semantics), ("needs_sample_semantics", samples)):
        expect(isinstance(value, bool), f"{name} is {value!r}, expected a bool")
    return semantics, samples


def inputs_for(loss: Any, **options: Any) -> LossInputs | ImageLossInputs:
    """The inputs the pipeline would give this loss set: semantic ones only where its flags ask for them."""
    semantics, samples = flags(loss)
    instances = bool(getattr(loss, "needs_instances", False))
    if instances:
        # K = slots + 1 logits; "one class" becomes one slot and one instance id.
        options["classes"] = max(2, int(options.get("classes", 5)))
        options["instance_ids"] = min(3, options["classes"] - 1)
    whole = bool(getattr(loss, "needs_whole_images", False))
    return loss_inputs(semantics=semantics, sample_semantics=samples, instances=instances, whole_image=whole,
                       **options)


def terms(loss: Any, inputs: LossInputs | ImageLossInputs, when: str = "") -> Outputs:
    """The loss set's terms, each a finite float scalar."""
    if isinstance(inputs, ImageLossInputs):
        absent = [n for n in ("scores", "semantic", "teacher_map", "logits") if getattr(inputs.output, n) is None]
    else:
        absent = [n for n in ("logits", "teacher_at_rays") if getattr(inputs, n) is None]
        if inputs.coarse.semantic is None:
            absent.append("semantic")
        if inputs.coarse.sample_semantic is None:
            absent.append("sample_semantic")
    what = "loss(inputs" + (f" without {', '.join(absent)}" if absent else "") + (f", {when}" if when else "") + ")"
    result = call(what, loss, inputs)
    expect(isinstance(result, dict) and result, f"{what} returned {result!r:.60}, expected a non-empty dict of terms")
    for name, value in result.items():
        expect(isinstance(name, str), f"{what} returned the term name {name!r}, expected a str")
        expect(isinstance(value, Tensor) and value.dim() == 0 and value.is_floating_point(),
               f"{what} term {name!r} is {shape(value)}, expected a float scalar tensor []")
    expect_finite(result, f"from {what}")
    return result


def check_flags(subject: Subject) -> None:
    """The loss set runs on exactly what its flags ask for, and every flag it sets is used.

    ``needs_sample_semantics`` implies ``needs_semantics``; a loss set that leaves ``needs_semantics`` False gets no
    logits, labels, teacher or semantic features (as in the pipeline), so one that reads them fails here.
    """
    loss = subject.build()
    semantics, samples = flags(loss)
    expect(semantics or not samples, "needs_sample_semantics is True but needs_semantics is False")
    inputs = inputs_for(loss)
    try:
        result = terms(loss, inputs, f"needs_semantics={semantics}, needs_sample_semantics={samples}")
    except CheckFailed as failure:
        if semantics and samples:
            raise  # it got everything: not a flag problem
        hint = "needs_semantics" if not semantics else "needs_sample_semantics"
        message = f"{failure}; a loss set that reads what its flags leave out (None) must set {hint} = True"
        raise CheckFailed(message) from None
    reached = reached_leaves(result, inputs)
    if semantics and not any(leaf.split(".")[-1] in SEMANTIC_LEAVES for leaf in reached):
        raise CheckFailed(f"needs_semantics is True but no term's gradient reaches the logits or the semantic "
                          f"features (terms reach: {', '.join(reached) or 'nothing'}); drop the flag or use them")
    if samples and not any(leaf.endswith("sample_semantic") for leaf in reached):
        raise CheckFailed(f"needs_sample_semantics is True but no term's gradient reaches sample_semantic "
                          f"(terms reach: {', '.join(reached) or 'nothing'})")


def check_labels(subject: Subject) -> None:
    """``needs_labels`` (default True) tells the truth where it is False: the terms are the same when every label is
    the ignore index, as on a scene without labels, and instance ids (labels too) are not asked for."""
    loss = subject.build()
    needs = call("reading needs_labels", lambda: getattr(loss, "needs_labels", True))
    expect(isinstance(needs, bool), f"needs_labels is {needs!r}, expected a bool")
    if needs:
        return
    expect(not getattr(loss, "needs_instances", False),
           "needs_labels is False but needs_instances is True; instance ids are labels, so set needs_labels = True")
    inputs = inputs_for(loss)
    if inputs.labels is None:
        return  # needs_semantics is False: the pipeline gives it no labels at all
    unlabelled = dataclasses.replace(inputs, labels=torch.full_like(inputs.labels, inputs.ignore_index))
    with_labels = terms(loss, inputs, "with labels")
    without = terms(loss, unlabelled, "with every label the ignore index, as on a scene without labels")
    expect(set(with_labels) == set(without),
           f"needs_labels is False but the terms change with the labels: {sorted(with_labels)} with labels, "
           f"{sorted(without)} with every label ignored; a loss set that reads labels must set needs_labels = True")
    for name, value in with_labels.items():
        value, other = value.detach(), without[name].detach()
        expect(torch.allclose(value, other, rtol=1e-5, atol=1e-7),
               f"needs_labels is False but term {name!r} changes when every label is ignored ({float(value):.6g} -> "
               f"{float(other):.6g}); a loss set that reads labels must set needs_labels = True")


def reached_leaves(result: Outputs, inputs: LossInputs | ImageLossInputs) -> list[str]:
    """The input tensors some term's gradient reaches."""
    leaves = loss_leaves(inputs)
    total = sum(result.values())
    if not isinstance(total, Tensor) or not total.requires_grad:
        return []
    grads = torch.autograd.grad(total, list(leaves.values()), allow_unused=True, retain_graph=True)
    return [name for name, grad in zip(leaves, grads) if grad is not None]


def check_terms(subject: Subject) -> None:
    """Non-empty dict of finite float scalars; with and without a fine pass."""
    loss = subject.build()
    for fine in (True, False):
        terms(loss, inputs_for(loss, fine=fine), "with a fine pass" if fine else "without a fine pass (fine=None)")


def check_gradients(subject: Subject) -> None:
    """Every term's gradient reaches some input it reads, and every parameter of the loss set."""
    loss = subject.build().train()
    inputs = inputs_for(loss)
    result = terms(loss, inputs)
    leaves = loss_leaves(inputs)
    for name, value in result.items():
        expect(value.requires_grad, f"term {name!r} does not require grad: it cannot train anything")
        grads = call(f"gradient of term {name!r}", torch.autograd.grad, value, list(leaves.values()),
                     allow_unused=True, retain_graph=True)
        expect(any(g is not None for g in grads), f"term {name!r}'s gradient reaches none of the inputs "
                                                  f"({', '.join(leaves)})")
    parameters = dict(loss.named_parameters())
    if parameters:
        call("backward of the sum of the terms", sum(result.values()).backward)
        missing = [n for n, p in parameters.items() if p.requires_grad and p.grad is None]
        expect(not missing, f"no gradient reached the loss set's parameters {', '.join(missing)}")


def check_modes(subject: Subject) -> None:
    probe = subject.build()
    inputs = inputs_for(probe)
    expect_modes(subject, lambda loss: terms(loss, inputs))


def check_degenerate(subject: Subject) -> None:
    """One class, every label ignored, all-zero features and unknown depth: finite terms and gradients."""
    loss = subject.build()
    cases = {
        "one class": dict(classes=1),
        "every label ignored": dict(ignore_all=True),
        "all-zero features, logits and depth": dict(zeros=True),
    }
    for when, options in cases.items():
        inputs = inputs_for(loss, **options)
        result = terms(loss, inputs, when)
        leaves = loss_leaves(inputs)
        total = sum(result.values())
        if total.requires_grad:
            grads = call("gradient of the terms' sum", torch.autograd.grad, total, list(leaves.values()),
                         allow_unused=True)
            expect_finite({f"gradient of {n}": g for n, g in zip(leaves, grads) if g is not None}, f"for {when}")


CHECKS = {
    "build": check_build,
    "flags": check_flags,
    "labels": check_labels,
    "terms": check_terms,
    "gradients": check_gradients,
    "train and eval": check_modes,
    "degenerate inputs": check_degenerate,
    "config round trip": check_round_trip,
}
