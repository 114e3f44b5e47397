"""The optimizer of a training run: Adam with one parameter group per learning-rate group a model family names.

A group's rate has one home, the family's ``model.lr.<group>``: its config's ``lr`` section declares every group its
``parameter_groups()`` names (the shared parts' ``feature_extractor`` and ``head`` too) with a default. Every trainable
parameter must be in exactly one group, and every group that trains must have a rate: one left out would never be
trained, one listed twice would be stepped twice (``check_parameter_groups``, the one check of that rule, which the
contract kit runs too).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.training import GroupOptions


def learning_rates(rates: Mapping[str, Any] | None) -> dict[str, float]:
    """Rates by group name: the family's ``model.lr`` (None when its config has no such section: no rates). A rate that
    is not a finite number > 0 is refused naming its key."""
    checked = {}
    for name, value in dict(rates or {}).items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"model.lr.{name}={value!r}: expected a finite learning rate > 0")
        checked[str(name)] = float(value)
    return checked


def check_parameter_groups(model: torch.nn.Module, groups: Mapping[str, list[torch.nn.Parameter]],
                           rates: Mapping[str, float]) -> None:
    """The rule of ``parameter_groups()``: every trainable parameter of ``model`` in exactly one group, and every group
    with a trainable parameter a rate in ``rates`` (the family's ``model.lr``); a ConfigError naming the family and
    the first parameter or group otherwise."""
    names = {id(p): n for n, p in model.named_parameters()}
    seen: dict[int, str] = {}
    family = type(model).__name__
    for group, params in groups.items():
        for p in params:
            if id(p) in seen and seen[id(p)] != group:
                raise ConfigError(f"model {family}: parameter {names.get(id(p), '?')!r} is in both learning-rate "
                                  f"groups {seen[id(p)]!r} and {group!r} of parameter_groups(); expected exactly one")
            seen[id(p)] = group
    missing = [n for n, p in model.named_parameters() if p.requires_grad and id(p) not in seen]
    if missing:
        raise ConfigError(f"model {family}: {len(missing)} trainable parameter(s) are in no learning-rate group of "
                          f"parameter_groups() and would never be trained (first: {missing[0]!r}); put each in "
                          "exactly one group, or set requires_grad=False")
    unrated = [name for name, params in groups.items() if name not in rates and any(p.requires_grad for p in params)]
    if unrated:
        raise ConfigError(f"model {family} trains a parameter group {unrated[0]!r} that model.lr has no rate for; "
                          f"model.lr has: {', '.join(rates) or 'nothing'} (its config's lr section declares every "
                          "group parameter_groups() names)")


def make_optimizer(model: torch.nn.Module, rates: Mapping[str, float],
                   options: Mapping[str, GroupOptions] | None = None) -> torch.optim.Optimizer:
    """Adam with one parameter group per learning-rate group of ``model.parameter_groups()`` at its rate in
    ``rates`` (``learning_rates`` of ``model.lr``); each optimizer group carries its ``name``, and its ``eps`` where
    ``options`` (the family's ``optimizer_options``) gives one."""
    named = model.parameter_groups()
    check_parameter_groups(model, named, rates)
    options = dict(options or {})
    unknown = [name for name in options if name not in named]
    if unknown:
        raise ConfigError(f"model {type(model).__name__}: optimizer_options() names the group {unknown[0]!r}, which "
                          f"parameter_groups() has not (it has: {', '.join(named)})")
    groups = []
    for name, params in named.items():
        params = [p for p in params if p.requires_grad]
        if not params:
            continue
        group = {"params": params, "lr": float(rates[name]), "name": name}
        if name in options and options[name].eps is not None:
            group["eps"] = float(options[name].eps)
        groups.append(group)
    return torch.optim.Adam(groups)


def make_scheduler(optimizer: torch.optim.Optimizer, shared: Callable[[int], float],
                   options: Mapping[str, GroupOptions] | None = None) -> torch.optim.lr_scheduler.LambdaLR:
    """The rate of each group of ``optimizer`` per step: the run's schedule ``shared`` (``schedule.lr_factor``), or a
    group's own ``GroupOptions.lr_factor``."""
    options = options or {}
    own = [options[g["name"]].lr_factor if g["name"] in options else None for g in optimizer.param_groups]
    if not any(own):
        return torch.optim.lr_scheduler.LambdaLR(optimizer, shared)
    return torch.optim.lr_scheduler.LambdaLR(optimizer, [factor or shared for factor in own])


def optimizer_problem(model: torch.nn.Module, optimizer: torch.optim.Optimizer, family: str | None = None
                      ) -> str | None:
    """What keeps ``optimizer`` from training ``model`` after a change of size (densification, a resume), in one
    sentence, or None: a tensor it steps that the model no longer has (parameters replaced without it), a trainable
    parameter in none of its groups (it would never train again), or a moment whose shape is not its parameter's.
    The one rule the trainer checks after a family changes size and on resume, and the contract kit after its steps.
    ``family``: its registry name, for the message (default: the class's).
    """
    family = family or getattr(model, "name", None) or type(model).__name__
    names = {id(p): n for n, p in model.named_parameters()}
    held = [p for group in optimizer.param_groups for p in group["params"]]
    stale = [p for p in held if id(p) not in names]
    if stale:
        return (f"model {family!r}: the optimizer steps {len(stale)} tensor(s) the model no longer has (shape "
                f"{list(stale[0].shape)}): parameters were replaced without the optimizer, so they stop training; "
                "resize them with gpnerf_core.resize_parameter (GaussianParameters.set_rows with the optimizer)")
    ids = {id(p) for p in held}
    missing = [n for n, p in model.named_parameters() if p.requires_grad and id(p) not in ids]
    if missing:
        return (f"model {family!r}: parameter {missing[0]!r} is in no optimizer group, so it would never train "
                "(resize parameters with gpnerf_core.resize_parameter, which hands the new tensor to the optimizer)")
    for p in held:
        for key, moment in optimizer.state.get(p, {}).items():
            if isinstance(moment, torch.Tensor) and moment.dim() > 0 and moment.shape != p.shape:
                return (f"model {family!r}: the optimizer's {key} of parameter {names[id(p)]!r} is "
                        f"{list(moment.shape)} for a parameter {list(p.shape)}: its moments did not follow its rows "
                        "(resize with gpnerf_core.resize_parameter and its kept rows)")
    return None
