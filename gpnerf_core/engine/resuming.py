"""Where a ``run`` (or ``finetune``) starts: ``train.resume`` turned into a checkpoint (``auto``: the newest intact one
of ``out_dir``) and every check of it that can refuse the resume, before the run folder is touched (``plan_resume``).
The checkpoint is read once: the plan hands its read to the trainer (``ResumePlan.take_read``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from gpnerf_core.errors import ConfigError, DataError, GpnerfError
from gpnerf_core.model.checkpoint import check_resume_config
from gpnerf_core.model.trained import TrainedModel, checked_checkpoint_path, load_trained
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.training.resume import newest_intact_checkpoint, run_checkpoints


@dataclass
class ResumePlan:
    """How a ``run`` starts: from ``checkpoint`` (None: from scratch), with notes to print; ``replace_leftovers``: the
    folder may hold files of an earlier attempt of this run that died before its first checkpoint (``resume=auto``),
    which the claim replaces."""

    checkpoint: Path | None
    notes: tuple[str, ...] = ()
    replace_leftovers: bool = False
    read: TrainedModel | None = field(default=None, repr=False, compare=False)
    """The checkpoint as ``plan_resume`` read it, until the trainer takes it (``take_read``)."""

    @property
    def resuming(self) -> bool:
        return self.checkpoint is not None

    def take_read(self) -> TrainedModel | None:
        """The checkpoint read, handed over once (``Trainer(..., resume_from=plan.take_read())``: the file is not read
        again); the plan keeps no reference, so its tensors go once they are in the model and the optimizer."""
        read, self.read = self.read, None
        return read


def plan_resume(cfg: DictConfig, dist: Distributed) -> ResumePlan:
    """Resolve ``train.resume`` (``auto``: rank 0 picks the newest intact checkpoint of ``out_dir`` and every rank takes
    the same) and check that the checkpoint can continue this config; ``cfg.train.resume`` becomes the path chosen.

    Every check of the checkpoint that refuses the resume runs before the run folder is touched: here the seed, the
    steps and (``train.resume_strict``) the model and loss config; the trainer's own (weights, optimizer state, weight
    average) run when it is built, which ``run`` does before it claims the folder.

    Raises:
        ConfigError: ``auto`` without ``out_dir``; another ``seed`` than the checkpoint's (its random streams go on,
            the new seed would be recorded but not used); ``train.steps`` below the checkpoint's step; another model
            or loss config (``check_resume_config``, unless ``train.resume_strict=false``).
        DataError: the checkpoint is missing, a folder or damaged; ``auto`` found only damaged ones.
    """
    value = cfg.train.resume
    if not value:
        return ResumePlan(None)
    notes: list[str] = []
    read = None
    if str(value) == "auto":
        if not cfg.out_dir:
            raise ConfigError("train.resume=auto needs out_dir=<folder>: the fixed folder a restarted job resumes in")
        outcome, read = _find_auto_checkpoint(Path(str(cfg.out_dir))) if dist.is_main else (None, None)
        outcome = dist.broadcast_object(outcome)  # the path: every other rank reads the file itself
        if outcome[0] == "error":
            raise DataError(outcome[1])
        found, notes = outcome[1], list(outcome[2])
        with open_dict(cfg):
            cfg.train.resume = found
        if found is None:
            notes.append(f"train.resume=auto: no checkpoint in {cfg.out_dir}; training from the start")
            return ResumePlan(None, tuple(notes), replace_leftovers=True)
        notes.append(f"train.resume=auto: resuming from {found}")
    path = checked_checkpoint_path(str(cfg.train.resume), "train.resume")
    if read is None:
        read = load_trained(path, "train.resume")
    state = read.state
    written = OmegaConf.create(state["config"]) if state.get("config") else OmegaConf.create({})
    if "seed" in written and int(written.seed) != int(cfg.seed):
        raise ConfigError(
            f"train.resume={path}: seed={int(cfg.seed)} differs from the checkpoint's seed={int(written.seed)}; a "
            "resumed run continues the checkpoint's random streams, so leave seed as it was or start a new run"
        )
    if int(cfg.train.steps) < int(state["step"]):
        raise ConfigError(
            f"train.resume={path}: train.steps={int(cfg.train.steps)} is below the step {int(state['step'])} the "
            "checkpoint reached; give train.steps >= that step (equal: evaluate it again)"
        )
    if cfg.train.resume_strict:  # another model or loss: refused here, before anything is written
        check_resume_config(path, state["config"], OmegaConf.to_yaml(cfg, resolve=True), True)
    return ResumePlan(path, tuple(notes), read=read)


def _find_auto_checkpoint(folder: Path) -> tuple[tuple[str, Any, Any], TrainedModel | None]:
    """``("ok", path or None, notes)`` for ``train.resume=auto`` in ``folder``, or ``("error", message, None)``; and
    the checkpoint read (None: none found).

    The newest checkpoint is read once, here, and its read kept for the resume; only when it is damaged are the older
    ones walked (``newest_intact_checkpoint``, whose notes name each damaged one), and the one found read again."""
    checkpoints = run_checkpoints(folder)
    try:
        if checkpoints:
            try:
                read = load_trained(checkpoints[-1][1])
                return ("ok", str(read.path), []), read
            except DataError:
                pass  # damaged: the walk below skips it, saying so
        found, notes = newest_intact_checkpoint(folder)
    except GpnerfError as exc:
        return ("error", str(exc), None), None
    if found is None and (folder / "metrics.json").exists():
        return ("error", f"train.resume=auto: {folder} holds a finished run's metrics.json but no checkpoint to "
                         "resume from; choose another out_dir, or overwrite=true to replace it", None), None
    return ("ok", None if found is None else str(found), notes), None
