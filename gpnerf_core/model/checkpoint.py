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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import torch
import yaml

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.runtime.io import atomic_torch_save
from gpnerf_core.runtime.versions import software_versions

FORMAT_VERSION = 2
"""Schema version of the checkpoint dictionary; bumped whenever a key changes meaning."""

MODEL_SECTIONS = ("feature_extractor", "field_aggregator", "ray_aggregator", "head", "loss", "model")
"""Config sections that define the model and its loss: resuming with other values is refused."""

NOT_MODEL_KEYS = (
    "model.init",
    "model.init_strict",
    "model.checkpoint_blocks",
    "model.channels_last_maps",
    "model.compile",
    "model.compile_backend",
)
"""Keys inside ``MODEL_SECTIONS`` that change how weights start or how memory is spent, not the model."""


@dataclass(frozen=True)
class RunRecord:
    """What a run was made from, written into each of its checkpoints.

    Attributes:
        config_yaml: the composed, resolved config.
        overrides: the Hydra overrides that composed it (``+head=unet``, ``train.steps=10``, ...).
        components: ``{kind: {"name", "provider", "version"}}`` of the components the config selects.
    """

    config_yaml: str
    overrides: tuple[str, ...]
    components: dict[str, dict[str, str]]

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
) -> Path:
    """Write a checkpoint atomically (a reader never sees half a file).

    Args:
        model: the model; the classes it predicts are stored from its ``classes`` attribute (a ``ClassList``, set by
            ``build_components``; None for a model built otherwise).
        rng_states: one ``{"cpu": ByteTensor, "cuda": ByteTensor | None}`` per process, in rank order.
        weight_average: ``WeightAverage.state_dict()`` when the run keeps one (``train.ema_decay``).
    """
    classes = getattr(model, "classes", None)
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
        "versions": software_versions(),
        "class_names": None if classes is None else [str(name) for name in classes.names],
        "ignore_index": None if classes is None else int(classes.ignore_index),
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


def verify_content(state: Mapping[str, Any], path: str | Path) -> None:
    """Raise DataError naming ``path`` when the checkpoint's contents differ from the hash written with them."""
    stored = state.get(DIGEST_KEY)
    if stored is None:
        return
    if content_digest(state) != stored:
        raise DataError(
            f"checkpoint {path} is damaged: its contents do not match the content_sha256 written with it "
            "(changed or corrupted bytes); use an earlier checkpoint of the run"
        )


def stored_classes(state: Mapping[str, Any], path: str | Path) -> tuple[tuple[str, ...], int] | None:
    """The class names and ignore index a checkpoint's model was trained with, or None when it stores none (written
    before checkpoints kept them, by a model built without ``build_components``, or by one trained without classes).

    Raises:
        DataError: the stored values are not a list of names and an integer.
    """
    names, ignore = state.get("class_names"), state.get("ignore_index")
    if names is None or (isinstance(names, (list, tuple)) and not names):
        return None
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise DataError(f"checkpoint {path}: class_names is {names!r:.80}; expected a list of class names")
    if not isinstance(ignore, int) or isinstance(ignore, bool):
        raise DataError(f"checkpoint {path}: ignore_index is {ignore!r}; expected an integer")
    return tuple(names), int(ignore)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a gpnerf-core checkpoint's dictionary safely (``weights_only``), with one-line errors."""
    path = Path(path)
    state = read_torch_file(path)
    if not isinstance(state, dict) or "format" not in state:
        raise DataError(f"checkpoint {path} is not a gpnerf-core checkpoint (no 'format' key)")
    if state["format"] != FORMAT_VERSION:
        raise DataError(
            f"checkpoint {path} has format {state['format']!r}; this gpnerf-core reads format {FORMAT_VERSION} "
            "(it was written by another version: evaluate it with that version, or retrain)"
        )
    verify_content(state, path)
    return state


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


def read_torch_file(path: Path) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU; a missing, truncated or foreign file is one line."""
    if not path.is_file():
        raise DataError(f"checkpoint {path} does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        text = str(exc).strip()
        reason = text.splitlines()[0].split(". ")[0] if text else type(exc).__name__
        if "weights_only" in str(exc) or "Unsupported global" in str(exc):
            reason = "it holds Python objects that are not weights (only tensors and plain containers load safely)"
        raise DataError(f"checkpoint {path} could not be read: {reason} (truncated or not a torch file?)") from None


def load_weights(module: torch.nn.Module, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Load ``state`` into ``module`` strictly; a missing, extra or differently shaped tensor is one line.

    Args:
        source: names where the weights came from in the error (a file path).
    """
    own = module.state_dict()
    missing = [key for key in own if key not in state]
    unexpected = [key for key in state if key not in own]
    if missing or unexpected:
        detail = f"missing {missing[0]!r}" if missing else f"unexpected {unexpected[0]!r}"
        raise DataError(
            f"{source} does not match the configured model: {detail} "
            f"({len(missing)} missing, {len(unexpected)} unexpected tensors)"
        )
    check_shapes(own, state, source)
    module.load_state_dict(state)


def check_shapes(own: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor], source: str) -> None:
    """Raise on the first tensor of ``state`` whose shape differs from ``own``'s, naming key and both shapes."""
    for key, value in state.items():
        if key in own and tuple(own[key].shape) != tuple(value.shape):
            raise DataError(
                f"{source}: tensor {key!r} has shape {list(value.shape)}, the configured model expects "
                f"{list(own[key].shape)} (a different model size?)"
            )


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


_ABSENT = "<absent>"


def _leaf_differences(old: Any, new: Any, prefix: str) -> list[tuple[str, Any, Any]]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in list(old) + [k for k in new if k not in old]:
            sub = f"{prefix}.{key}" if prefix else str(key)
            out += _leaf_differences(old.get(key, _ABSENT), new.get(key, _ABSENT), sub)
        return out
    return [] if old == new else [(prefix, old, new)]


def format_differences(differences: list[tuple[str, Any, Any]], limit: int = 12) -> str:
    """``key: old -> new`` joined by ``; `` (at most ``limit``, then a count)."""
    parts = [f"{key}: {old!r} -> {new!r}" for key, old, new in differences[:limit]]
    if len(differences) > limit:
        parts.append(f"... and {len(differences) - limit} more")
    return "; ".join(parts)


def check_resume_config(path: Path, checkpoint_yaml: str, config_yaml: str, strict: bool) -> list[str]:
    """Compare the model and loss sections of a checkpoint's config with this run's.

    Returns:
        Lines describing accepted differences (``strict`` False); raises ConfigError when ``strict``.
    """
    differences = config_differences(checkpoint_yaml, config_yaml, MODEL_SECTIONS, NOT_MODEL_KEYS)
    if not differences:
        return []
    if strict:
        raise ConfigError(
            f"train.resume={path}: the checkpoint was trained with another model or loss config "
            f"({format_differences(differences)}); use the same settings, or train.resume_strict=false to resume anyway"
        )
    return [f"resuming despite config differences: {format_differences(differences)}"]
