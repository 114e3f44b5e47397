"""What a process does with a config before any work, the one way every command and tool does it: compose and
validate it (``compose_checked``), then set torch's threads and seed and choose the device (``setup_process``).

A config is validated once per command and process: before Hydra (``launching.precheck``), or in the job that was not
prechecked (``start``); ``size`` and ``bench`` validate what they compose (``compose_checked``). Hydra jobs set up
their process in ``start`` (``run``; ``eval``, ``finetune``, ``render``, ``view``, ``export``, ``label``, ``stress`` and
the viewer's timing through ``opening.open_trained``); ``bench`` (its ``measure``, ``profile``, ``ab``) and ``size``
call ``setup_process`` themselves.
"""

from __future__ import annotations

import re

from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from gpnerf_core.config.compose import compose
from gpnerf_core.config.presets import check_presets
from gpnerf_core.engine.sweeps import refuse_shared_out_dir
from gpnerf_core.engine.validation import validate_config
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.kinds import GROUPS
from gpnerf_core.runtime.device import resolve_device
from gpnerf_core.runtime.host_memory import keep_freed_memory


def compose_checked(overrides: list[str]) -> DictConfig:
    """The config ``overrides`` compose (``compose_overrides``), validated (``check_config``): an unknown component,
    an override Hydra cannot apply and a value the schema refuses are each one ``GpnerfError`` (for the commands that
    are not Hydra jobs)."""
    cfg = compose_overrides(overrides)
    check_config(cfg)
    return cfg


def compose_overrides(overrides: list[str]) -> DictConfig:
    """The config ``overrides`` compose, not validated yet; an unknown component and an override Hydra cannot apply
    are each one ``GpnerfError``."""
    check_component_choices(overrides, get_registry())
    check_override_grammar(overrides)
    try:
        return compose(overrides)
    except GpnerfError:
        raise
    except Exception as exc:
        raise ConfigError(hydra_message(exc)) from None


def check_config(cfg: DictConfig) -> None:
    """``validate_config``, after every interpolation resolves: one that does not (``train.steps=${oops}``) is one
    ``ConfigError`` naming the key, the value as typed and why."""
    problem = unresolvable_interpolation(cfg)
    if problem is not None:
        key, raw, reason = problem
        raise ConfigError(f"{key}={raw}: the interpolation cannot be resolved ({reason}); "
                          "${...} must name a key of the config, e.g. ${train.rays}")
    try:
        validate_config(cfg)
    except InterpolationResolutionError as exc:  # one unresolvable_interpolation does not reach (a resolver's own)
        raise ConfigError(hydra_message(exc)) from None


def unresolvable_interpolation(node: Any, prefix: str = "") -> tuple[str, str, str] | None:
    """``(dotted key, value as typed, reason)`` of the first interpolation in ``node`` that does not resolve (None:
    all do). ``${hydra:...}`` is skipped outside a Hydra job, where it cannot resolve yet."""
    keys = node.keys() if isinstance(node, DictConfig) else range(len(node)) if isinstance(node, ListConfig) else ()
    for key in keys:
        path = f"{prefix}{key}" if isinstance(node, DictConfig) else f"{prefix.rstrip('.')}[{key}]"
        if OmegaConf.is_interpolation(node, key):
            raw = str(node._get_node(key)._value())
            if "${hydra:" in raw.replace(" ", ""):
                continue
            try:
                node[key]
            except InterpolationResolutionError as exc:
                return path, raw, hydra_message(exc)
            continue
        child = node._get_node(key)
        if isinstance(child, (DictConfig, ListConfig)) and not child._is_missing() and not child._is_none():
            found = unresolvable_interpolation(child, f"{path}.")
            if found is not None:
                return found
    return None


def check_override_grammar(overrides: list[str]) -> None:
    """Refuse an override Hydra's grammar cannot read in one line naming it and how to quote it (Hydra's own message
    names neither)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for override in overrides:
        try:
            parser.parse_override(override)
        except Exception as exc:
            key, sep, value = override.partition("=")
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0].split(" See https://")[0]
            advice = (f"put the value in quotes, as one shell argument: \"{key}='{value}'\"" if sep and value
                      else "expected key=value")
            raise ConfigError(f"{override}: Hydra's override grammar cannot read it ({first}); {advice}") from None


def check_component_choices(argv: list[str], registry: Any) -> None:
    """Refuse ``[+]head=<name>`` (and every other component group) naming no registered component, in one line that
    lists the known names and any plugin that failed to load, before Hydra says only "could not find"; and a plugin's
    config preset that shadows a built-in one (``config.presets.check_presets``)."""
    check_presets(registry)
    for argument in argv:
        key, sep, value = argument.partition("=")
        group = key.lstrip("+~")
        if not sep or group not in GROUPS or "${" in value:
            continue
        for name in value.split(","):  # a -m sweep over options
            name = name.strip()
            if name and name != "null" and not any(c in name for c in "*?[("):
                registry.get(GROUPS[group], name)


MULTIPLE_VALUES = re.compile(r"Multiple values for (\w+)\. To override a value use 'override \w+: (\S+)'")
FOREIGN_KEY = re.compile(r"In '([\w/]+)': ConfigKeyError raised while composing config:\s*Key '(\w+)' not in '(\w+)'")


def hydra_message(exc: BaseException) -> str:
    """A Hydra/OmegaConf error and its causes on one line, without OmegaConf's ``full_key``/``object_type`` tail; the
    errors a user meets most, said in this project's terms (``+loss=x`` where an experiment chose a loss already)."""
    chosen = MULTIPLE_VALUES.search(str(exc))
    if chosen is not None:
        group, option = chosen.groups()
        return (f"+{group}={option}: the config already selects a {group} (an experiment's or a checkpoint's); replace "
                f"it with {group}={option} (without '+'), or leave the experiment out")
    foreign = FOREIGN_KEY.search(str(exc))
    if foreign is not None:  # an experiment's setting for a part that a group override (loss=x) replaced
        where, key, schema = foreign.groups()
        return (f"'{where}' sets {key} for the parts it chooses, and {schema} (chosen by an override of yours) has no "
                f"{key}: an override like loss=<name> replaced the experiment's choice; keep the experiment's, or leave "
                f"the experiment out")
    parts: list[str] = []
    while exc is not None:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        lines = [line for line in lines if not line.startswith(("full_key:", "object_type=", "reference_type="))]
        text = " ".join(lines)
        if text and text not in parts:
            parts.append(text)
        exc = exc.__cause__
    return "; ".join(parts) or "invalid overrides"


def start(cfg: DictConfig, *, validated: bool = False) -> torch.device:
    """A job's start, before any work: validate ``cfg`` unless it was (``validated``: before Hydra, ``precheck``),
    refuse one fixed ``out_dir`` for a whole ``-m`` sweep, then ``setup_process``; returns its device."""
    if not validated:
        check_config(cfg)
    refuse_shared_out_dir(cfg)
    return setup_process(cfg, validated=True)


def setup_process(cfg: DictConfig, *, validated: bool = False) -> torch.device:
    """Validate ``cfg`` (``check_config``) unless the caller did (``validated``), give torch ``cfg.threads`` threads
    (0: its default), keep freed host memory in the process when ``cfg.keep_freed_memory`` (``runtime.host_memory``)
    and seed torch with ``cfg.seed`` (which fixes every model's initialisation); returns the device ``cfg.device``
    resolves to."""
    if not validated:
        check_config(cfg)
    if cfg.keep_freed_memory:
        keep_freed_memory()
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    return resolve_device(cfg.device)
