"""Run folders read back: one table from many of them (a sweep, an ablation, seeds), for ``report``, ``stress`` and
``size``.

Rows are the run folders found below the given paths (any folder holding ``metrics.json`` and ``config.yaml``); a
folder holding ``config.yaml`` without ``metrics.json`` is a row of its own, ``failed`` (a sweep job's ``error.json``)
or ``unfinished`` (a run that failed, was stopped or killed, or still runs: ``unfinished_reason`` says which its files
show), never left out in silence. Runs
whose configs differ only by ``seed`` (and by where or how they ran: ``out_dir``, ``threads``, ``device``, ...) form
one row: each cell is the mean +- sample standard deviation over its runs, with n. Metric columns are keyed on the
evaluator's protocol ids (``miou/image_mean_present``, ``psnr/clamped``).

A run's method is named by its family's declaration (``ComponentSpec.display_name``: ``GP-NeRF``, ``Semantic-Ray``,
``NeuRay + semantic head``, ...); the report knows no family by its registry name. A row gets the paper's Table 4 ID
and numbers only when it is the paper's method (``GP-NeRF``, with the built-in ``unet`` head and a built-in loss set
``ce``, ``sd`` or ``dgs``) with that row's switches; a third-party head or loss set never sits beside the paper's
number. A row gets the paper's Table 1 mIoU (Replica / ScanNet) when its method is one of that table's rows by name,
trained with its cross-entropy (``+experiment=baselines/<name>``), or GP-NeRF with every Table 4 switch on. The
paper's numbers are Replica and ScanNet at full size: context, not a target for CPU-sized runs.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import socket
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from gpnerf_core.config.legacy import DEFAULT_MODEL, upgrade_config_yaml
from gpnerf_core.errors import DataError
from gpnerf_core.runtime.run_folder import LOCK_NAME
from gpnerf_core.training.resume import run_checkpoints

# Table 4 of the paper: (joint attention, S.D, gradient block, D.G) -> (ID, mIoU, PSNR) on ScanNet.
PAPER_TABLE4 = {
    (False, False, False, False): ("1", 56.45, 29.06),
    (True, False, False, False): ("2", 57.19, 29.30),
    (True, True, False, False): ("3", 52.03, 29.29),
    (True, True, True, False): ("4", 59.55, 29.26),
    (True, True, True, True): ("5", 59.92, 29.37),
}
PAPER_METHOD = "GP-NeRF"
"""The paper's own method, by name: Table 4's rows are its ablations."""
# Table 1 of the paper, generalization to unseen scenes: the method as the paper names it (a family's display name)
# -> mIoU on (Replica, ScanNet).
PAPER_TABLE1 = {
    "MVSNeRF + semantic head": (23.41, 39.82),
    "NeuRay + semantic head": (35.90, 51.03),
    "Semantic-Ray": (41.59, 57.15),
    PAPER_METHOD: (48.53, 59.92),
}
# Table 1's fine-tuning rows, the same columns: a run of ``finetune`` (its metrics carry a ``finetune`` curve), and a
# per-scene family's run (Semantic-NeRF has only this setting: fitted on one scene, scored on its held-out frames).
PAPER_TABLE1_FINETUNED = {
    "MVSNeRF + semantic head": (53.77, 55.26),
    "NeuRay + semantic head": (63.73, 77.48),
    "Semantic-Ray": (75.96, 91.06),
    PAPER_METHOD: (87.72, 93.84),
}
PAPER_TABLE1_PER_SCENE = {
    "Semantic-NeRF": (75.06, 91.24),
}
PAPER_HEADS = ("unet",)
PAPER_LOSS_SETS = ("ce", "sd", "dgs")
NOT_METHOD_KEYS = ("seed", "out_dir", "overwrite", "threads", "keep_freed_memory", "device", "checkpoint", "finetune",
                   "render", "view", "export", "label")
"""Top-level config keys that say where or how a run ran (or belong to other commands), not what it computes: runs
differing only there group."""
NOT_METHOD_TRAIN_KEYS = ("resume", "resume_strict", "loggers", "log_every")

# (column title, split, protocol id, scale, digits)
METRIC_COLUMNS = (
    ("mIoU held-out", "train_heldout", "miou/image_mean_present", 100.0, 2),
    ("mIoU unseen", "unseen", "miou/image_mean_present", 100.0, 2),
    ("PSNR held-out", "train_heldout", "psnr/clamped", 1.0, 2),
    ("AP@0.75 held-out", "train_heldout", "instance/ap_matched@0.75", 100.0, 2),
    ("COCO AP held-out", "train_heldout", "instance/coco_mask_ap", 100.0, 2),
)


@dataclass(frozen=True)
class RunRow:
    folder: Path
    config: dict[str, Any]
    metrics: dict[str, Any]
    error: str | None = None
    """Why a run has no metrics: a failed sweep job's ``error.json`` message, or what the files of an unfinished run
    folder show (``unfinished_reason``)."""
    state: str = "finished"
    """``finished`` (``metrics.json``), ``failed`` (``error.json``) or ``unfinished`` (neither)."""

    @property
    def semantic_field(self) -> dict[str, Any] | None:
        """The run's ``model.semantic_field`` (its family's defaults filled in) where its family's config has GP-NeRF's
        attention-reusing semantic field (``semantic_field.joint_attention``), whose switches Table 4's rows are; else
        None."""
        entry = _registry_for(self.config).components["model"].get(self.model)
        default = getattr(entry.spec.config(), "semantic_field", None) if entry is not None else None
        if default is None or not hasattr(default, "joint_attention"):
            return None
        own = (self.config.get("model") or {}).get("semantic_field") or {}
        return {**dataclasses.asdict(default), **own} if dataclasses.is_dataclass(default) else dict(own)

    def switches(self) -> tuple[bool | None, bool, bool, bool] | None:
        """Table 4's switches (joint attention, S.D, gradient block, D.G) of any run whose loss config carries them
        (a built-in loss set, or a third-party one with ``sd_weight`` / ``dgs_weight``), whatever its head; else None.
        Joint attention is the semantic field's switch: None for a family without one."""
        loss = self.config.get("loss") or {}
        if loss.get("name") not in PAPER_LOSS_SETS and not {"sd_weight", "dgs_weight"} & set(loss):
            return None
        semantic_field = self.semantic_field
        joint = bool(semantic_field.get("joint_attention", True)) if semantic_field is not None else None
        sd = float(loss.get("sd_weight", 0)) > 0
        dgs = float(loss.get("dgs_weight", 0)) > 0
        block = bool(loss.get("teacher_stop_grad", False)) and (sd or dgs)
        return joint, sd, block, dgs

    def paper_switches(self) -> tuple[bool | None, bool, bool, bool] | None:
        """``switches`` for the paper's method only (``PAPER_METHOD`` with its semantic field, ``PAPER_HEADS`` x
        ``PAPER_LOSS_SETS``): what gets a Table 4 ID. Another family decoded by the U-Net head with GP-NeRF's losses is
        not a Table 4 row."""
        loss = self.config.get("loss") or {}
        head = self.config.get("head") or {}
        if loss.get("name") not in PAPER_LOSS_SETS or head.get("name") not in PAPER_HEADS:
            return None
        if self.semantic_field is None or method_name(self) != PAPER_METHOD:
            return None
        return self.switches()

    @property
    def model(self) -> str:
        """The run's model family (the default for runs written before families were plugins)."""
        return str((self.config.get("model") or {}).get("name") or DEFAULT_MODEL)

    @property
    def evaluated(self) -> bool:
        """A run of ``eval`` (a trained checkpoint scored again: its metrics name the checkpoint)."""
        return "checkpoint" in self.metrics and not self.fine_tuned

    @property
    def fine_tuned(self) -> bool:
        """A run of ``finetune`` (a generalizable model fitted further on one scene)."""
        return "finetune" in self.metrics

    def paper_table1(self) -> tuple[float, float] | None:
        """The paper's Table 1 mIoU (Replica, ScanNet) of the method this run is, or None: the generalization row, the
        fine-tuning row for a ``finetune`` run, or for a per-scene family its per-scene row (Semantic-NeRF's own MLP
        only: its grid option is not the paper's)."""
        table = PAPER_TABLE1_FINETUNED if self.fine_tuned else PAPER_TABLE1
        name = method_name(self)
        if name == PAPER_METHOD:
            return table[PAPER_METHOD] if self.paper_switches() == (True, True, True, True) else None
        loss = (self.config.get("loss") or {}).get("name")
        if loss != "ce":
            return None
        return PAPER_TABLE1_PER_SCENE.get(name) or table.get(name)

    def method_key(self) -> str:
        """The config without the keys that do not change what the run computes (the seed among them), and whether it
        is a ``finetune`` run. A key of the schema's sections (``model``, ``train``, ...) that a run's config lacks
        takes today's default, and empty values (``[]``, ``""``, None) count as absent, so runs written before an
        option existed group with runs written after that leave it at its default."""
        config = {k: v for k, v in with_schema_defaults(self.config).items() if k not in NOT_METHOD_KEYS}
        if isinstance(config.get("train"), dict):
            config["train"] = {k: v for k, v in config["train"].items() if k not in NOT_METHOD_TRAIN_KEYS}
        if self.fine_tuned:  # a fine-tuned model is another row than the model it started from
            config["fine_tuned"] = True
        elif self.evaluated:  # an eval of a checkpoint is that model again, not another seed of it
            config["evaluation_of_a_checkpoint"] = True
        return json.dumps(_without_empty(config), sort_keys=True, default=str)


def _schema_defaults() -> dict[str, Any]:
    from omegaconf import OmegaConf

    from gpnerf_core.config.schema import RootConfig

    defaults = OmegaConf.to_container(OmegaConf.structured(RootConfig), throw_on_missing=False)
    return {k: v for k, v in defaults.items() if isinstance(v, dict)}


@functools.cache
def _builtin_registry() -> Any:
    """The built-in plugins' registry alone (no entry point imported)."""
    from gpnerf_core.registry.components import collect
    from gpnerf_core.registry.plugins import make_plugin_manager

    return collect(make_plugin_manager(autoload=False))


def _registry_for(config: dict[str, Any]) -> Any:
    """The built-in registry where it has every component ``config`` names, else the full one: reading runs of the
    built-in components imports no third-party plugin (one that is slow to import costs every ``report``)."""
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.registry.kinds import KINDS, section

    builtin = _builtin_registry()
    nodes = {kind: section(config, kind) for kind in KINDS}
    named = [(kind, str(node["name"])) for kind, node in nodes.items() if isinstance(node, dict) and node.get("name")]
    return builtin if all(name in builtin.components[kind] for kind, name in named) else get_registry()


def _component_defaults(config: dict[str, Any]) -> dict[str, Any]:
    """The defaults of each component section's registered config (``model``, ``head``, ...), by the name it holds; a
    part's inside the model's (``model.feature_extractor``)."""
    from gpnerf_core.registry.kinds import KINDS, section

    registry = _registry_for(config)
    defaults: dict[str, Any] = {}
    for kind in KINDS:
        node = section(config, kind)
        entry = registry.components[kind].get(str(node.get("name"))) if isinstance(node, dict) else None
        if entry is None:
            continue
        values = _plain(dataclasses.asdict(entry.spec.config()))
        if KINDS[kind].part:  # after the model's own (KINDS lists the model first)
            defaults.setdefault("model", {})[kind] = values
        else:
            defaults[kind] = values
    return defaults


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def with_schema_defaults(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` with the keys its schema sections and component sections lack filled in from today's defaults."""

    def fill(value: Any, default: Any) -> Any:
        if not isinstance(value, dict) or not isinstance(default, dict):
            return value
        return {**default, **{k: fill(v, default.get(k)) for k, v in value.items()}}

    defaults = {**_schema_defaults(), **_component_defaults(config)}
    return {k: fill(v, defaults.get(k)) for k, v in config.items()}


def _without_empty(value: Any) -> Any:
    if isinstance(value, dict):
        kept = {k: _without_empty(v) for k, v in value.items()}
        return {k: v for k, v in kept.items() if v not in (None, "", [], {})}
    if isinstance(value, list):
        return [_without_empty(v) for v in value]
    return value


@dataclass(frozen=True)
class RowGroup:
    """Runs of one method that differ only by seed."""

    runs: tuple[RunRow, ...]

    @property
    def label(self) -> str:
        names = [run.folder.name for run in self.runs]
        return names[0] if len(names) == 1 else f"{names[0]} (+{len(names) - 1})"

    @property
    def seeds(self) -> list[Any]:
        return [run.config.get("seed", "?") for run in self.runs]


def find_runs(paths: list[Path]) -> list[RunRow]:
    rows = []
    for path in paths:
        if not path.exists():
            raise DataError(f"{path}: expected a run folder or a folder of runs, found nothing")
        for error_file in sorted(path.rglob("error.json")):
            folder = error_file.parent
            if (folder / "metrics.json").exists() or not (folder / "config.yaml").is_file():
                continue
            try:
                message = str(json.loads(error_file.read_text()).get("error", "unknown error"))
                config = yaml.safe_load(upgrade_config_yaml((folder / "config.yaml").read_text())) or {}
            except (json.JSONDecodeError, yaml.YAMLError, AttributeError):
                message, config = f"{error_file} could not be parsed", {}
            rows.append(RunRow(folder, config if isinstance(config, dict) else {}, {}, error=message, state="failed"))
        rows += _unfinished_runs(path)
        for metrics_file in sorted(path.rglob("metrics.json")):
            folder = metrics_file.parent
            config_file = folder / "config.yaml"
            if not config_file.is_file():
                continue
            try:
                metrics = json.loads(metrics_file.read_text())
                config = yaml.safe_load(upgrade_config_yaml(config_file.read_text()))
            except (json.JSONDecodeError, yaml.YAMLError, UnicodeDecodeError) as exc:
                raise DataError(f"{metrics_file}: could not be parsed ({type(exc).__name__})") from None
            problem = metrics_shape_problem(metrics) or (
                None if isinstance(config, dict) else f"{config_file.name} holds a {type(config).__name__}")
            if problem is not None:
                raise DataError(f"{metrics_file}: not a gpnerf-core run's metrics ({problem}); expected what run, eval "
                                "or finetune writes")
            rows.append(RunRow(folder, config, metrics))
    return sorted(rows, key=lambda row: str(row.folder))


OTHER_RECORDS = ("metrics.json", "error.json", "render.json", "export.json", "bench.json")
"""Files that make a folder with ``config.yaml`` something other than an unfinished run: a finished run or eval, a
failed sweep job, a render, an export, a benchmark."""


def _unfinished_runs(path: Path) -> list[RunRow]:
    """Rows of the run folders below ``path`` that hold ``config.yaml`` but none of ``OTHER_RECORDS``."""
    rows = []
    for config_file in sorted(path.rglob("config.yaml")):
        folder = config_file.parent
        if any((folder / name).exists() for name in OTHER_RECORDS):
            continue
        try:
            config = yaml.safe_load(upgrade_config_yaml(config_file.read_text()))
        except (yaml.YAMLError, UnicodeDecodeError, OSError):
            config = None
        if not isinstance(config, dict) or "train" not in config:
            continue  # not a run's config (Hydra's own, another program's)
        rows.append(RunRow(folder, config, {}, error=unfinished_reason(folder, config), state="unfinished"))
    return rows


def unfinished_reason(folder: Path, config: dict[str, Any]) -> str:
    """What the files of a run folder without ``metrics.json`` show: still running, or stopped before its first
    checkpoint, during training (at which step) or after training (in evaluation)."""
    running = _live_holder(folder)
    if running:
        return f"no metrics.json yet: {running}"
    checkpoints = run_checkpoints(folder)
    if not checkpoints:
        return "no metrics.json and no checkpoint: it stopped (failed, interrupted or killed) before its first checkpoint"
    step, newest = checkpoints[-1]
    steps = (config.get("train") or {}).get("steps")
    if isinstance(steps, int) and step < steps:
        return (f"no metrics.json: training stopped at step {step} of {steps} (newest checkpoint "
                f"{newest.relative_to(folder)}); resume it with train.resume=auto out_dir={folder}")
    return (f"no metrics.json: training finished ({newest.relative_to(folder)}) but evaluation did not (failed, "
            "interrupted or killed)")


def _live_holder(folder: Path) -> str | None:
    """``held by a running process (pid N ...)`` when ``folder``'s lock names a live process of this machine."""
    try:
        holder = json.loads((folder / LOCK_NAME).read_text())
        pid, host = int(holder["pid"]), str(holder.get("host"))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if host != socket.gethostname():
        return f"locked by pid {pid} on {host} (running there, or killed without releasing {LOCK_NAME})"
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # another user's live process
    return f"held by a running process (pid {pid}, since {holder.get('started', '?')})"


NUMBER_OR_NONE = (int, float, type(None))


def metrics_shape_problem(metrics: Any) -> str | None:
    """What makes ``metrics`` unlike a run's ``metrics.json`` in the parts ``report`` reads, or None: an object whose
    ``eval`` maps splits to objects of metrics (numbers, or nested objects and lists), ``train`` an object whose
    ``steps`` and ``seconds`` are numbers, and ``eval_curve`` a list of objects with a numeric ``step``."""
    if not isinstance(metrics, dict):
        return f"it holds a {type(metrics).__name__}, not an object"
    evaluated = metrics.get("eval", {})
    if not isinstance(evaluated, dict):
        return f"'eval' is a {type(evaluated).__name__}"
    for split, values in evaluated.items():
        if not isinstance(values, dict):
            return f"'eval.{split}' is a {type(values).__name__}"
        for key, value in values.items():
            if "/" in key and not isinstance(value, (*NUMBER_OR_NONE, dict, list, str)):
                return f"'eval.{split}.{key}' is a {type(value).__name__}"
            if "/" in key and isinstance(value, str) and not key.endswith("reason"):
                return f"'eval.{split}.{key}' is text, not a number"
    train = metrics.get("train", {})
    if not isinstance(train, dict):
        return f"'train' is a {type(train).__name__}"
    for key in ("steps", "seconds", "rays_per_second"):
        if not isinstance(train.get(key), NUMBER_OR_NONE) or isinstance(train.get(key), bool):
            return f"'train.{key}' is a {type(train.get(key)).__name__}, not a number"
    curve = metrics.get("eval_curve")
    if curve is not None and (not isinstance(curve, list) or not all(
            isinstance(e, dict) and isinstance(e.get("step"), (int, float)) for e in curve)):
        return "'eval_curve' is not a list of objects with a numeric step"
    return None


def group_runs(rows: list[RunRow]) -> list[RowGroup]:
    """Runs grouped by ``method_key``, in the order their first run was found."""
    groups: dict[str, list[RunRow]] = {}
    for row in rows:
        key = f"{row.state}:{row.folder}" if row.error is not None else row.method_key()
        groups.setdefault(key, []).append(row)
    return [RowGroup(tuple(runs)) for runs in groups.values()]


def summarize(values: list[float], scale: float = 1.0, digits: int = 2) -> str:
    """``mean`` for one value, ``mean +- std (n=k)`` (sample standard deviation) for several, ``n/a`` for none."""
    if not values:
        return "n/a"
    scaled = [v * scale for v in values]
    mean = statistics.fmean(scaled)
    if len(scaled) == 1:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} +- {statistics.stdev(scaled):.{digits}f} (n={len(scaled)})"


def _metric(run: RunRow, split: str, key: str) -> float | None:
    value = run.metrics.get("eval", {}).get(split, {}).get(key)
    return None if value is None else float(value)


def format_table(rows: list[RunRow]) -> str:
    header = (
        "| run | seeds | model | head | loss | joint attn | S.D | grad block | D.G | steps | "
        + " | ".join(title for title, *_ in METRIC_COLUMNS)
        + " | train s | Table 4 ID | paper mIoU | paper PSNR | paper Table 1 mIoU (Replica / ScanNet) |"
    )
    width = header.count("|") - 1
    lines = [header, "|" + "|".join(["---"] * width) + "|"]
    for group in group_runs(rows):
        first = group.runs[0]
        if first.error is not None:
            lines.append(f"| {group.label} | " + f"{first.state}: {first.error}".replace("|", "/") + " |" + " |" * (width - 2))
            continue
        switches = first.switches()
        paper = PAPER_TABLE4.get(first.paper_switches()) if first.paper_switches() else None
        flags = ["-" if s is None else "yes" if s else "no" for s in switches] if switches else ["-"] * 4
        head = (first.config.get("head") or {}).get("name", "-")
        loss = (first.config.get("loss") or {}).get("name", "-")
        steps = sorted({str(run.metrics.get("train", {}).get("steps", "-")) for run in group.runs})
        metric_cells = []
        for _, split, key, scale, digits in METRIC_COLUMNS:
            values = [v for run in group.runs if (v := _metric(run, split, key)) is not None]
            metric_cells.append(summarize(values, scale, digits))
        seconds = [float(s) for run in group.runs if (s := run.metrics.get("train", {}).get("seconds")) is not None]
        table1 = first.paper_table1()
        cells = [
            group.label,
            ",".join(str(seed) for seed in group.seeds),
            first.model,
            head,
            loss,
            *flags,
            "/".join(steps),
            *metric_cells,
            summarize(seconds, digits=1),
            paper[0] if paper else "-",
            f"{paper[1]:.2f}" if paper else "-",
            f"{paper[2]:.2f}" if paper else "-",
            f"{table1[0]:.2f} / {table1[1]:.2f}" if table1 else "-",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def fronts_possible(method: Any) -> bool:
    """The method has a point on at least one (accuracy, cost) panel."""
    from gpnerf_core.tools.reporting.speed_accuracy import ACCURACY, COSTS

    return any(a.name in method.points for a in ACCURACY) and any(c.name in method.points for c in COSTS)


def method_name(row: RunRow) -> str:
    """The method a run is, as its family declares it (``ComponentSpec.display_name``): ``GP-NeRF``, ``GNT``
    (GP-NeRF's field without semantics), ``Semantic-Ray``, ``NeuRay + semantic head``, ``MVSNeRF + unet head``, ...; a
    family that declares a name (or none: its registry name) with a ``+head`` is ``<name> + <head> head``."""
    entry = _registry_for(row.config).components["model"].get(row.model)
    declared = entry.spec.display_name if entry is not None else ""
    if callable(declared):
        return str(declared(row.config))
    head = (row.config.get("head") or {}).get("name")
    name = declared or row.model
    return f"{name} + {head} head" if head is not None else name


def method_labels(groups: list[RowGroup]) -> list[str]:
    """Legend entries, one per group: the method's name, then its variant (head + loss for GP-NeRF, with the Table 4
    ID of the paper's rows; the loss set for the others); where several groups share that text, each also names its
    own values of the config keys that tell them apart (its size: blocks, samples, views, bounds, ...), and the first
    run's folder only where the configs name nothing."""
    described = []
    for group in groups:
        first = group.runs[0]
        head = (first.config.get("head") or {}).get("name")
        # without a loss set a run trained on its family's own terms alone (a 2D detector's)
        loss = (first.config.get("loss") or {}).get("name", "own loss terms")
        switches = first.paper_switches()
        paper = PAPER_TABLE4.get(switches) if switches else None
        # The semantic field's variants are named by head and loss (Table 4's rows); another method's name says its head
        variant = f"{head or 'no head'} + {loss}" if first.semantic_field is not None else loss
        variant += f", Table 4 ID {paper[0]}" if paper else ""
        described.append(f"{method_name(first)} ({variant})" + sampling_label(first.config))
    labels = []
    for text, group in zip(described, groups):
        twins = [g for t, g in zip(described, groups) if t == text]
        if len(twins) == 1:
            labels.append(text)
            continue
        differences = distinguishing_values(group, twins)
        labels.append(f"{text} [{differences or group.runs[0].folder.name}]")
    return labels


def sampling_label(config: dict[str, Any]) -> str:
    """`` (depth samples: <source>)`` for a run with ``model.sampler=depth`` (the source: its ``+depth_source`` or the
    first pass), "" for the default sampling."""
    if (config.get("model") or {}).get("sampler") != "depth":
        return ""
    source = (config.get("depth_source") or {}).get("name", "first pass")
    return f" (depth samples: {source})"


def distinguishing_values(group: RowGroup, twins: list[RowGroup], most: int = 4) -> str:
    """``key=value`` of ``group`` for the config keys whose values differ among ``twins`` (keys by their last part,
    so ``model.field_aggregator.num_blocks=2`` reads ``num_blocks=2``; the model's size first), at most ``most`` of them,
    then ``+N more``."""
    defaults = _flatten(_without_empty(_schema_defaults()))  # sections a run's config lacks read as the defaults
    flat = [{**defaults, **_flatten(json.loads(twin.runs[0].method_key()))} for twin in twins]
    keys = sorted(set().union(*flat), key=lambda key: (_SIZE_ORDER.get(key.split(".")[0], len(_SIZE_ORDER)), key))
    value = lambda config, key: json.dumps(config.get(key), sort_keys=True)  # noqa: E731
    differing = [key for key in keys if len({value(f, key) for f in flat}) > 1]
    own = flat[next(i for i, twin in enumerate(twins) if twin is group)]
    shown = differing[:most]
    # Then what still tells this group from a twin that the first keys do not (labels stay unique).
    for other in flat:
        if other is not own and all(value(other, key) == value(own, key) for key in shown):
            shown += [next(key for key in differing if value(other, key) != value(own, key))]
    parts = [f"{key.rsplit('.', 1)[-1]}={_short(own.get(key, '-'))}" for key in shown]
    if len(differing) > len(shown):
        parts.append(f"+{len(differing) - len(shown)} more")
    return ", ".join(parts)


_SIZE_ORDER = {section: rank for rank, section in enumerate(
    ("model", "dataset", "train", "loss", "head"))}
"""Sections named first in a label: the model's size before the data, the recipe and the rest."""


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(value, dict):
        return {prefix: value}
    out: dict[str, Any] = {}
    for key, item in value.items():
        out.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _short(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def with_parameter_count(row: RunRow) -> RunRow:
    """Runs written before ``metrics.json`` held ``parameters``: count the model tensors of their final checkpoint."""
    if row.error is not None or "parameters" in row.metrics:
        return row
    checkpoint = (row.metrics.get("train") or {}).get("checkpoint")
    if not checkpoint or not Path(checkpoint).is_file():
        return row
    from gpnerf_core.errors import DataError
    from gpnerf_core.model.checkpoint import read_torch_file

    try:  # weights only: a report never runs code from a file it reads
        state = read_torch_file(Path(checkpoint))
    except DataError:
        return row
    state = state.get("model", {}) if isinstance(state, dict) else {}
    total = sum(t.numel() for t in state.values() if hasattr(t, "numel"))
    return RunRow(row.folder, row.config, {**row.metrics, "parameters": {"total": total}}, row.error, row.state)
