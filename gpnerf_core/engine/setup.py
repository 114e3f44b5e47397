"""What a process does with a config before any work, the one way every command and tool does it: compose and
validate it (``compose_checked``), then set torch's threads and seed and choose the device (``setup_process``).

``run``, ``eval``, ``finetune``, ``render`` and ``view`` go through it in ``jobs.start``; ``bench`` (and its
``measure``, ``profile``, ``ab``), ``size``, ``stress`` and the viewer's timing call it directly.
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig

from gpnerf_core.config.compose import compose
from gpnerf_core.engine.validation import validate_config
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.runtime.device import resolve_device


def compose_checked(overrides: list[str]) -> DictConfig:
    """The config ``overrides`` compose, validated; an unknown component, an override Hydra cannot apply and a value
    the schema refuses are each one ``GpnerfError`` (for ``precheck`` and the commands that are not Hydra jobs)."""
    check_component_choices(overrides, get_registry())
    try:
        cfg = compose(overrides)
    except GpnerfError:
        raise
    except Exception as exc:
        raise ConfigError(hydra_message(exc)) from None
    validate_config(cfg)
    return cfg


def check_component_choices(argv: list[str], registry: Any) -> None:
    """Refuse ``[+]head=<name>`` (and every other component group) naming no registered component, in one line that
    lists the known names and any plugin that failed to load, before Hydra says only "could not find"."""
    for argument in argv:
        key, sep, value = argument.partition("=")
        group = key.lstrip("+~")
        if not sep or group not in KINDS or "${" in value:
            continue
        for name in value.split(","):  # a -m sweep over options
            name = name.strip()
            if name and name != "null" and not any(c in name for c in "*?[("):
                registry.get(group, name)


def hydra_message(exc: BaseException) -> str:
    """A Hydra/OmegaConf error and its causes on one line, without OmegaConf's ``full_key``/``object_type`` tail."""
    parts: list[str] = []
    while exc is not None:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        lines = [line for line in lines if not line.startswith(("full_key:", "object_type=", "reference_type="))]
        text = " ".join(lines)
        if text and text not in parts:
            parts.append(text)
        exc = exc.__cause__
    return "; ".join(parts) or "invalid overrides"


def setup_process(cfg: DictConfig) -> torch.device:
    """Validate ``cfg`` (``validate_config``), give torch ``cfg.threads`` threads (0: its default) and seed it with
    ``cfg.seed`` (which fixes every model's initialisation); returns the device ``cfg.device`` resolves to."""
    validate_config(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    return resolve_device(cfg.device)
