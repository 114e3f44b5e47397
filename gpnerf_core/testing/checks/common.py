"""What every check shares: the component under test, failures that name shapes, and the kind-independent rules
(build, gradients to every parameter, train/eval modes, finite outputs, config round trip)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import torch
from omegaconf import OmegaConf
from torch import Tensor, nn

from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.registry.components import RegisteredComponent, Registry
from gpnerf_core.registry.plugins import one_line

Outputs = dict[str, Tensor]
"""Named output tensors of one call of a component (``logits``, ``block 0 view_attention``, ...)."""


class CheckFailed(Exception):
    """The component broke the rule a check tests; the message says how, with the shapes involved."""


class CheckSkipped(Exception):
    """The check cannot run here (a dataset whose files are absent); the message says why."""


@dataclass(frozen=True)
class Subject:
    """One registered component under test.

    Attributes:
        kind, name: registry kind and name.
        entry: the registry's record (spec, provider, version).
        registry: the registry it came from (builds it the way the pipeline does).
        config: config fields that replace the dataclass defaults (small sizes for a fast check).
        runtime: the keyword arguments the pipeline would pass (``ComponentKind.runtime_arguments``), at the kit's sizes.
    """

    kind: str
    name: str
    entry: RegisteredComponent
    registry: Registry
    config: Mapping[str, Any] = field(default_factory=dict)
    runtime: Mapping[str, Any] = field(default_factory=dict)
    part_configs: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """A model family's: the kit's ``configs`` of part components (``{"feature_extractor/<name>": {...}}``), which the
    parts its config declares are built with (``inputs.kit_parts``)."""

    @property
    def label(self) -> str:
        return component_label(self.kind, self.name, self.entry.provider, self.entry.version)

    def node(self) -> dict[str, Any]:
        """The config node the checks build from: the name and the overridden fields (a model family renders few
        samples per ray unless told otherwise: ``inputs.KIT_SAMPLES``)."""
        from gpnerf_core.testing.inputs import KIT_SAMPLES

        samples = {}
        if self.kind == "model":  # a ray-marching family's sample counts (RayMarchingConfig)
            fields = {f.name for f in dataclasses.fields(self.entry.spec.config)}
            samples = {key: value for key, value in KIT_SAMPLES.items() if key in fields}
        return {"name": self.name, **samples, **self.config}

    def kit_parts(self, *, head: bool) -> Any:
        """A model family's ``ModelParts``: the parts its config declares, with the options its config under check and
        the kit's ``configs`` give them (``inputs.kit_parts``), and the kit's head when ``head``."""
        from gpnerf_core.testing.inputs import kit_parts

        return kit_parts(self.registry, self.name, head=head, parts=self.node(), configs=self.part_configs)

    @property
    def predicts_instances(self) -> bool:
        """A head whose class declares ``predicts = Predicts.INSTANCES`` (``num_outputs = slots + 1``, at least 2)."""
        predicts = getattr(self.entry.spec.factory, "predicts", Predicts.CLASSES)
        return self.kind == "head" and Predicts(predicts) is Predicts.INSTANCES

    @property
    def takes_head(self) -> bool:
        """A model family that decodes with a head (``Capabilities.accepts_head``); other kinds: True."""
        if self.kind != "model":
            return True
        model = self.build(parts=self.kit_parts(head=False))
        return bool(model.capabilities.accepts_head)

    def build(self, node: Mapping[str, Any] | None = None, **runtime: Any) -> Any:
        """Build through the registry with ``runtime`` replacing the kit's runtime arguments.

        ``node`` replaces the kit's config node (the round-tripped config). A failure names the arguments and the
        factory's own error (without the registry's prefix, which repeats the component's name).
        """
        arguments = {**self.runtime, **runtime}
        if self.kind == "model" and "parts" not in arguments:
            arguments["parts"] = self.kit_parts(head=self.takes_head)
        where = "building" + (" from the round-tripped config" if node is not None else "")
        where += f" with {describe(arguments)}" if arguments and node is None else ""
        node = self.node() if node is None else node
        if self.predicts_instances and "num_outputs" in arguments:
            # An instance head's num_outputs comes from its config, as in the pipeline: slots + 1.
            node = {**{str(k): v for k, v in node.items()}, "slots": int(arguments["num_outputs"]) - 1}
        try:
            return self.registry.build(self.kind, node, **arguments)
        except Exception as exc:
            message = one_line(exc).removeprefix(f"{self.entry.where} failed to build: ")
            raise CheckFailed(f"{where} raised {message if message != one_line(exc) else _named(exc)}") from exc


def component_label(kind: str, name: str, plugin: str, version: str) -> str:
    """``head 'fancy' (plugin gpnerf_head_fancy 0.1.0)``, as the registry names a component."""
    return f"{kind} {name!r} (plugin {plugin} {version})"


def _named(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {one_line(exc)}"


def describe(values: Mapping[str, Any]) -> str:
    return ", ".join(f"{key}={value}" for key, value in values.items())


def shape(tensor: Any) -> str:
    """``[1, 3, 16, 24]`` for a tensor, the type name for anything else."""
    return str(list(tensor.shape)) if isinstance(tensor, Tensor) else type(tensor).__name__


def call(what: str, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call into the component; any exception it raises fails the check with ``what`` naming the inputs."""
    try:
        return function(*args, **kwargs)
    except (CheckFailed, CheckSkipped):
        raise
    except Exception as exc:
        raise CheckFailed(f"{what} raised {_named(exc)}") from exc


def expect(condition: bool, message: str) -> None:
    if not condition:
        raise CheckFailed(message)


def expect_tensor(
    value: Any, what: str, expected_shape: list[int] | None = None, dtype: torch.dtype | None = None
) -> Tensor:
    """``value`` is a tensor (of ``expected_shape`` and ``dtype`` when given); returns it."""
    expect(isinstance(value, Tensor), f"{what} is {type(value).__name__}, expected a tensor")
    if expected_shape is not None:
        expect(list(value.shape) == expected_shape, f"{what} {shape(value)}, expected {expected_shape}")
    if dtype is not None:
        expect(value.dtype == dtype, f"{what} has dtype {value.dtype}, expected {dtype}")
    return value


def expect_finite(outputs: Outputs, when: str) -> None:
    for name, tensor in outputs.items():
        bad = ~torch.isfinite(tensor.detach())
        if tensor.dim() == 0 and bool(bad):
            raise CheckFailed(f"{name} is {float(tensor.detach())} {when}")
        if bool(bad.any()):
            where = [int(i) for i in bad.nonzero()[0]]
            raise CheckFailed(f"{name} {shape(tensor)} has {int(bad.sum())} NaN/Inf values (first at {where}) {when}")


def expect_sums_to_one(
    weights: Tensor, dim: int, what: str, mask: Tensor | None = None, when: str = "", atol: float = 1e-4
) -> None:
    """Non-negative and summing to 1 along ``dim`` (only where ``mask``, shaped as the sum, is True)."""
    w = weights.detach().double()
    when = f" {when}" if when else ""
    expect(bool((w >= -atol).all()), f"{what} {shape(weights)} has negative values (min {float(w.min()):.3g}){when}")
    error = (w.sum(dim) - 1).abs()
    if mask is not None:
        error = error[mask]
    if error.numel() and float(error.max()) > atol:
        worst = float(error.max())
        raise CheckFailed(f"{what} {shape(weights)} sums to {1 + worst:.6g} (off by {worst:.3g}) along dim {dim}, "
                          f"expected 1{when}")


def total(outputs: Outputs) -> Tensor:
    """The sum of every output, the scalar the gradient checks differentiate."""
    return sum(t.float().sum() for t in outputs.values() if t.is_floating_point())


def expect_gradients(module: Any, outputs: Outputs, inputs: Mapping[str, Tensor] | None = None) -> None:
    """After a backward of the sum of ``outputs``, every parameter and every named input has a finite gradient."""
    inputs = inputs or {}
    scalar = total(outputs)
    expect(isinstance(scalar, Tensor) and scalar.requires_grad,
           f"no output requires grad (outputs: {', '.join(f'{k} {shape(v)}' for k, v in outputs.items())})")
    call("backward of the sum of the outputs", scalar.backward)
    parameters = dict(module.named_parameters()) if isinstance(module, nn.Module) else {}
    missing = [name for name, p in parameters.items() if p.requires_grad and p.grad is None]
    missing += [f"input {name}" for name, t in inputs.items() if t.grad is None]
    if missing:
        raise CheckFailed(
            f"no gradient reached {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''} "
            f"({len(missing)} of {len(parameters) + len(inputs)}) after a backward of the sum of "
            f"{', '.join(f'{k} {shape(v)}' for k, v in outputs.items())}"
        )
    grads = {name: p.grad for name, p in parameters.items() if p.grad is not None}
    expect_finite({f"gradient of {name}": g for name, g in grads.items()}, "after a backward of the outputs")


def expect_modes(subject: Subject, run: Callable[[Any], Outputs]) -> None:
    """``run(component)`` works in train mode, and in eval mode gives the same outputs twice."""
    component = subject.build()
    if not isinstance(component, nn.Module):
        return
    component.train()
    trained = call("forward in train mode", run, component)
    component.eval()
    with torch.no_grad():
        first = call("forward in eval mode", run, component)
        second = run(component)
    expect_finite(trained, "in train mode")
    expect_finite(first, "in eval mode")
    for name, tensor in first.items():
        expect(list(trained[name].shape) == list(tensor.shape),
               f"{name} is {shape(trained[name])} in train mode but {shape(tensor)} in eval mode")
        if not torch.equal(tensor, second[name]):
            diff = float((tensor.double() - second[name].double()).abs().max())
            raise CheckFailed(f"{name} {shape(tensor)} differs between two eval-mode calls (max {diff:.3g}): "
                              f"eval mode must be deterministic")


def plain(value: Any) -> Any:
    """Tuples as lists, as they come back from OmegaConf, so equal configs compare equal."""
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    return value


def round_tripped(subject: Subject) -> dict[str, Any]:
    """The subject's config through ``OmegaConf.structured`` -> YAML -> back onto the schema (as Hydra loads it)."""
    schema = subject.entry.spec.config
    try:
        original = schema(**subject.config)
    except TypeError as exc:
        raise CheckFailed(f"the kit's config for it does not fit {schema.__name__}: {one_line(exc)}") from None
    try:
        text = OmegaConf.to_yaml(OmegaConf.structured(original))
        back = OmegaConf.merge(OmegaConf.structured(schema), OmegaConf.create(text))
    except Exception as exc:
        raise CheckFailed(f"OmegaConf cannot represent {schema.__name__}: {_named(exc)}") from None
    values = OmegaConf.to_container(back, resolve=True)
    before = plain(dataclasses.asdict(original))
    changed = [key for key in before if values.get(key) != before[key]]
    if changed:
        key = changed[0]
        raise CheckFailed(f"{schema.__name__}.{key} = {before[key]!r} comes back from YAML as {values.get(key)!r}")
    return values


def check_round_trip(subject: Subject) -> None:
    """The config survives Hydra's round trip, and the component builds from the round-tripped node."""
    node = round_tripped(subject)
    try:
        direct = subject.build()
    except CheckFailed:
        if subject.kind == "dataset":
            return  # a dataset may need its files to build; the values round-tripped
        raise
    rebuilt = subject.build(node)
    if isinstance(direct, nn.Module):
        before = {k: list(v.shape) for k, v in direct.state_dict().items()}
        after = {k: list(v.shape) for k, v in rebuilt.state_dict().items()}
        if before != after:
            key = next(k for k in sorted(before.keys() | after.keys()) if before.get(k) != after.get(k))
            raise CheckFailed(f"built from the round-tripped config, {key} is {after.get(key)}; from the config "
                              f"itself it is {before.get(key)}")


def check_build(subject: Subject) -> None:
    """Builds with the kit's config and runtime arguments; parameters start finite."""
    component = subject.build()
    if isinstance(component, nn.Module):
        expect_finite({f"parameter {k}": p for k, p in component.named_parameters()}, "after construction")
