"""Checkpoints that explain themselves and resume exactly.

A checkpoint holds the model, optimizer and schedule, the step, every process's random state and the step
sampler's, and what made it: the composed config (YAML) and its hash, the Hydra overrides that composed it,
the components used (kind, name, provider, version), the software versions, and the classes its head predicts
(``class_names``, ``ignore_index``: what ``eval``, ``render`` and ``finetune`` use on a dataset without a class list;
absent from checkpoints written before they were stored, which still load). It is loaded with
``torch.load(weights_only=True)``: nothing in it is unpickled as code.

Every checkpoint also carries ``content_sha256``, a hash of everything else in it (``content_digest``), checked on every
load: torch's zip reader does not check the CRCs of the tensors it reads, so a flipped byte inside a weight would
otherwise load, evaluate and resume without a word. Checkpoints written before the hash was stored load unchecked.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import torch
import yaml

from gpnerf_core.config.legacy import upgrade_config_yaml, upgrade_overrides, upgrade_sections
from gpnerf_core.config.schema import ModelConfig
from gpnerf_core.errors import ConfigError, DataError, PluginError
from gpnerf_core.model.classes import ClassList
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.runtime.io import atomic_torch_save
from gpnerf_core.runtime.versions import software_versions

FORMAT_VERSION = 2
"""Schema version of the checkpoint dictionary; bumped whenever a key changes meaning."""


def model_sections() -> tuple[str, ...]:
    """Config sections that define the model and its loss (``ComponentKind.defines_model``; the parts are inside
    ``model``'s): resuming or fine-tuning with other values is refused, ``eval`` restores the checkpoint's."""
    return tuple(kind.name for kind in KINDS.values() if kind.defines_model)


def runtime_keys(config_yaml: str) -> tuple[str, ...]:
    """Dotted keys inside the model sections that change how weights start, or how time and memory are spent, not the
    model: the ``runtime_keys`` of the config's model family (``ModelConfig.runtime_keys`` for an unknown one)."""
    name = ((yaml.safe_load(config_yaml) or {}).get("model") or {}).get("name")
    registered = get_registry().components["model"].get(str(name))
    config = registered.spec.config if registered is not None else ModelConfig
    return tuple(f"model.{key}" for key in getattr(config, "runtime_keys", ModelConfig.runtime_keys))


def model_differences(
    old_yaml: str, new_yaml: str, sections: Iterable[str] | None = None
) -> list[tuple[str, Any, Any]]:
    """``config_differences`` of the model sections, runtime keys left out, and keys the checkpoint predates left out:
    an option added since takes its default, and a new option's default is the behaviour before it existed (the
    project's rule for new options), so a checkpoint stays resumable and evaluable as it was trained.

    Args:
        sections: the sections that define the checkpoint's model (``checkpoint_sections``); None: every section of a
            kind that can define one (``model_sections``).
    """
    wanted = model_sections() if sections is None else tuple(sections)
    return [(key, old, new) for key, old, new in
            config_differences(old_yaml, new_yaml, wanted, runtime_keys(new_yaml)) if old != ABSENT]


def checkpoint_sections(state: Mapping[str, Any]) -> tuple[str, ...]:
    """The config sections that define a checkpoint's model: those its run recorded (the model, the loss and the parts
    its family built), or, for a checkpoint written before they were recorded, every kind that can define one."""
    recorded = state.get("model_sections")
    return tuple(str(s) for s in recorded) if isinstance(recorded, (list, tuple)) and recorded else model_sections()


@dataclass(frozen=True)
class RunRecord:
    """What a run was made from, written into each of its checkpoints.

    Attributes:
        config_yaml: the composed, resolved config.
        overrides: the Hydra overrides that composed it (``+head=unet``, ``train.steps=10``, ...).
        components: ``{kind: {"name", "provider", "version"}}`` of the components the config selects.
        model_sections: the config sections that define the model (``build.model_sections``), or None when not known
            (a benchmark's record).
    """

    config_yaml: str
    overrides: tuple[str, ...]
    components: dict[str, dict[str, str]]
    model_sections: tuple[str, ...] | None = None

    @property
    def config_sha256(self) -> str:
        return hashlib.sha256(self.config_yaml.encode()).hexdigest()


def save_checkpoint(
    path: Path,
    *,
    record: RunRecord,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    step: int,
    sampler: Mapping[str, Any],
    rng_states: list[dict[str, Any]],
    history: list[dict[str, float]],
    elapsed: float,
    weight_average: Mapping[str, Any] | None = None,
    classes: ClassList | None = None,
    scenes: tuple[str, ...] | None = None,
) -> Path:
    """Write a checkpoint atomically (a reader never sees half a file).

    Args:
        model: the model.
        classes: the classes it predicts (``Components.classes``), stored so that ``eval``, ``render`` and
            ``finetune`` name them on a dataset that has none; None stores none.
        rng_states: one ``{"cpu": ByteTensor, "cuda": ByteTensor | None}`` per process, in rank order.
        scenes: the scenes it was trained on (a per-scene model renders only those), or None.
        weight_average: ``WeightAverage.state_dict()`` when the run keeps one (``train.ema_decay``).
    """
    state = {
        "format": FORMAT_VERSION,
        "step": step,
        "model": model.state_dict(),
        "weight_average": dict(weight_average) if weight_average is not None else None,
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "sampler": dict(sampler),
        "rng": list(rng_states),
        "history": history,
        "elapsed": elapsed,
        "config": record.config_yaml,
        "config_sha256": record.config_sha256,
        "overrides": list(record.overrides),
        "components": record.components,
        "model_sections": list(record.model_sections) if record.model_sections else None,
        "versions": software_versions(),
        "class_names": None if classes is None else [str(name) for name in classes.names],
        "ignore_index": None if classes is None else int(classes.ignore_index),
        "scenes": None if scenes is None else [str(name) for name in scenes],
    }
    state["content_sha256"] = content_digest(state)
    return atomic_torch_save(path, state)


DIGEST_KEY = "content_sha256"


def content_digest(state: Mapping[str, Any]) -> str:
    """sha256 of a checkpoint dictionary without its ``content_sha256``: tensors by dtype, shape and bytes, other values
    by type and ``repr``, dictionaries in key order (sorted by ``repr``), so a reloaded dictionary hashes the same."""
    digest = hashlib.sha256()
    _digest_value(digest, {key: value for key, value in state.items() if key != DIGEST_KEY})
    return digest.hexdigest()


def _digest_value(digest: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        flat = value.detach().to("cpu").contiguous().reshape(-1)
        digest.update(f"tensor:{flat.dtype}:{tuple(value.shape)}:".encode())
        digest.update(flat.view(torch.uint8).numpy().tobytes() if flat.numel() else b"")
    elif isinstance(value, Mapping):
        digest.update(f"dict:{len(value)}:".encode())
        for key in sorted(value, key=repr):
            digest.update(f"{key!r}=".encode())
            _digest_value(digest, value[key])
    elif isinstance(value, (list, tuple)):  # a tuple may come back as a list: hash both alike
        digest.update(f"list:{len(value)}:".encode())
        for item in value:
            _digest_value(digest, item)
    else:
        digest.update(f"{type(value).__name__}:{value!r};".encode())


def verify_content(state: Mapping[str, Any], path: str | Path, label: str | None = None) -> None:
    """Raise DataError naming ``path`` when the checkpoint's contents differ from the hash written with them.

    Args:
        label: how the file is named in the error (default ``checkpoint <path>``; ``model.init=<path>``).
    """
    stored = state.get(DIGEST_KEY)
    if stored is None:
        return
    if content_digest(state) != stored:
        raise DataError(
            f"{label or f'checkpoint {path}'} is damaged: its contents do not match the content_sha256 written with it "
            "(changed or corrupted bytes); use an earlier checkpoint of the run"
        )


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a gpnerf-core checkpoint's dictionary safely (``weights_only``), with one-line errors; ``checked_state``."""
    path = Path(path)
    return checked_state(read_torch_file(path), path)


def checked_state(state: Any, path: str | Path, label: str | None = None) -> dict[str, Any]:
    """What every reader of a gpnerf-core checkpoint checks of its dictionary: a checkpoint, of this format version, its
    contents matching their hash; configs written by earlier versions are then brought to today's keys.

    Args:
        label: how the file is named in errors (default ``checkpoint <path>``; ``model.init=<path>``).
    """
    label = label or f"checkpoint {path}"
    if not isinstance(state, dict) or "format" not in state:
        raise DataError(f"{label} is not a gpnerf-core checkpoint (no 'format' key)")
    if state["format"] != FORMAT_VERSION:
        raise DataError(
            f"{label} has format {state['format']!r}; this gpnerf-core reads format {FORMAT_VERSION} "
            "(it was written by another version: evaluate it with that version, or retrain)"
        )
    verify_content(state, path, label)
    if isinstance(state.get("config"), str):
        state["config"] = upgrade_config_yaml(state["config"])
    if isinstance(state.get("overrides"), list):
        model = ((yaml.safe_load(state.get("config") or "") or {}).get("model") or {}).get("name")
        state["overrides"] = upgrade_overrides([str(o) for o in state["overrides"]], model)
    if isinstance(state.get("model_sections"), list):
        state["model_sections"] = list(upgrade_sections(str(s) for s in state["model_sections"]))
    return state


def check_recorded_components(state: Mapping[str, Any], path: str | Path) -> None:
    """Refuse a checkpoint whose components (``RunRecord.components``) no loaded plugin registers, in one line naming
    the distribution and version it recorded and how to get it back (before Hydra says only "unknown head").

    Raises:
        PluginError: a recorded component is not registered here (uninstalled, disabled or failed to load).
    """
    registry = get_registry()
    for kind, used in (state.get("components") or {}).items():
        if kind not in registry.components or not isinstance(used, Mapping) or "name" not in used:
            continue
        name = str(used["name"])
        if name in registry.components[kind] or f"{kind}/{name}" in registry.clashes:
            continue
        provider, version = str(used.get("provider", "unknown")), str(used.get("version", "unknown"))
        distribution = str(used.get("distribution") or provider)
        raise PluginError(f"{kind} {name!r} of checkpoint {path} comes from {distribution} {version} (plugin "
                          f"{provider}), {_why_missing(registry, provider, distribution, version)}")


def _why_missing(registry: Any, provider: str, distribution: str, version: str) -> str:
    """Why a recorded plugin registers nothing here: not installed, disabled, failed to load, or another version; and
    the fix."""
    pinned = f"'{distribution}=={version}'" if version not in ("unknown", "") else f"'{distribution}'"
    try:
        installed = importlib.metadata.version(distribution)
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return f"which is not installed; pip install {pinned}"
    disabled = [d for d in registry.disabled if d == provider or d.startswith((f"{provider} ", "every entry point"))]
    if disabled:
        return (f"which is installed but disabled here ({disabled[0]}): unset GPNERF_DISABLE_PLUGINS / "
                "GPNERF_DISABLE_PLUGIN_AUTOLOAD")
    failed = [p for p in registry.problems if p.plugin.name == provider and p.component is None]
    if failed:
        return f"which failed to load: {failed[0].reason}"
    return f"but the installed {distribution} {installed} does not register it; pip install {pinned}"


WEIGHT_CHOICES = ("average", "trained")


def evaluation_weights(state: Mapping[str, Any], choice: str = "average") -> tuple[dict[str, torch.Tensor], str]:
    """The weights a checkpoint is evaluated with, and which they are.

    Args:
        choice: ``average``: the run's weight average where it kept one (``train.ema_decay``), else the trained
            weights; ``trained``: the weights of the last optimizer step.

    Returns:
        ``(state dict, "average" | "trained")``.
    """
    if choice not in WEIGHT_CHOICES:
        raise ConfigError(f"eval.weights={choice!r}: expected one of {', '.join(WEIGHT_CHOICES)}")
    average = state.get("weight_average")
    if choice == "average" and average is not None:
        return dict(average["weights"]), "average"
    return dict(state["model"]), "trained"


def read_torch_file(path: Path, label: str | None = None) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU; a missing, truncated or foreign file is one line naming it as
    ``label`` says (default ``checkpoint <path>``; ``model.init=<path>``)."""
    label = label or f"checkpoint {path}"
    if not path.is_file():
        raise DataError(f"{label} does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        text = str(exc).strip()
        reason = text.splitlines()[0].split(". ")[0] if text else type(exc).__name__
        if "weights_only" in str(exc) or "Unsupported global" in str(exc):
            reason = "it holds Python objects that are not weights (only tensors and plain containers load safely)"
        raise DataError(f"{label} could not be read: {reason} (truncated or not a torch file?)") from None


def config_differences(
    old_yaml: str, new_yaml: str, sections: Iterable[str] | None = None, ignore: Iterable[str] = ()
) -> list[tuple[str, Any, Any]]:
    """``(dotted key, old value, new value)`` for every leaf that differs between two config YAMLs.

    Args:
        sections: compare only these top-level sections (None: everything).
        ignore: dotted keys (and their subtrees) left out.
    """
    old, new = yaml.safe_load(old_yaml) or {}, yaml.safe_load(new_yaml) or {}
    if sections is not None:
        wanted = tuple(sections)
        old = {k: v for k, v in old.items() if k in wanted}
        new = {k: v for k, v in new.items() if k in wanted}
    ignored = tuple(ignore)
    return [
        (key, a, b)
        for key, a, b in _leaf_differences(old, new, "")
        if not any(key == i or key.startswith(i + ".") for i in ignored)
    ]


ABSENT = "<absent>"
"""A key one of two compared configs does not have (``config_differences``)."""


def _leaf_differences(old: Any, new: Any, prefix: str) -> list[tuple[str, Any, Any]]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in list(old) + [k for k in new if k not in old]:
            sub = f"{prefix}.{key}" if prefix else str(key)
            out += _leaf_differences(old.get(key, ABSENT), new.get(key, ABSENT), sub)
        return out
    return [] if old == new else [(prefix, old, new)]


def format_differences(differences: list[tuple[str, Any, Any]], limit: int = 12) -> str:
    """``key: old -> new`` joined by ``; `` (at most ``limit``, then a count)."""
    parts = [f"{key}: {old!r} -> {new!r}" for key, old, new in differences[:limit]]
    if len(differences) > limit:
        parts.append(f"... and {len(differences) - limit} more")
    return "; ".join(parts)


def check_resume_config(path: Path, checkpoint_yaml: str, config_yaml: str, strict: bool,
                        sections: Iterable[str] | None = None) -> list[str]:
    """Compare the model and loss sections of a checkpoint's config with this run's (``sections``: those defining the
    checkpoint's model, ``checkpoint_sections``; None: every kind that can).

    Returns:
        Lines describing accepted differences (``strict`` False); raises ConfigError when ``strict``.
    """
    differences = model_differences(checkpoint_yaml, config_yaml, sections)
    if not differences:
        return []
    if strict:
        raise ConfigError(
            f"train.resume={path}: the checkpoint was trained with another model or loss config "
            f"({format_differences(differences)}); use the same settings, or train.resume_strict=false to resume anyway"
        )
    return [f"resuming despite config differences: {format_differences(differences)}"]
