"""Shared by the tests: compose tiny configs and train and evaluate a tiny GP-NeRF through the real pipeline."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch

from gpnerf_core.cli import main as cli_main
from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.evaluation.evaluator import evaluate
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer

TINY_MODEL = [
    "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16",
    "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "train.steps=2", "train.log_every=1", "eval.chunk_rays=256", "eval.save_images=1", "threads=1",
]

TINY_SCENES = [
    "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.height=32", "dataset.width=48",
]


def make_trainer(cfg, run_dir: Path, dist: Distributed | None = None, components=None, resume_from=None) -> Trainer:
    """A Trainer on ``cfg`` writing to ``run_dir`` (single CPU process unless ``dist`` is given; ``resume_from``: the
    checkpoint ``train.resume`` names, read already)."""
    from omegaconf import OmegaConf

    record = RunRecord(config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overrides=(), components={})
    components = components or build_components(cfg)
    return Trainer(cfg, components, dist=dist or Distributed.single(), run_dir=run_dir, record=record,
                   resume_from=resume_from)


def train_and_evaluate(dataset_overrides: list[str], run_dir: Path) -> dict:
    """Compose ``+head=unet +loss=dgs`` with the dataset overrides, train 2 steps, evaluate; returns the metrics."""
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *dataset_overrides])
    torch.manual_seed(0)
    components = build_components(cfg)
    trainer = make_trainer(cfg, run_dir, components=components)
    result = trainer.fit(progress=False)
    assert result.steps == 2 and all(torch.isfinite(torch.tensor(h["loss"])) for h in result.history)
    return evaluate(cfg, components, trainer.frames, run_dir, Distributed.single())


def assert_both_splits_scored(metrics: dict, num_classes: int) -> None:
    """Both evaluation splits scored at least one image, with an mIoU in [0, 1] over ``num_classes`` classes."""
    for split in ("train_heldout", "unseen"):
        values = metrics["eval"][split]
        assert values["count/images"] >= 1 and 0.0 <= values["miou/image_mean_present"] <= 1.0
        assert len(values["iou/dataset_per_class"]) == num_classes


TINY_CLI = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.num_train_scenes=1", "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4",
    "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "threads=1", "eval.save_images=0",
]
"""A tiny run through the command line: one 32x48 layout, a small model (the subprocess tests' overrides)."""

KIT_PARTS = {
    "feature_extractor": {"name": "resunet_fpn", "widths": [8, 8, 8, 16], "fpn_channels": 4},
    "field_aggregator": {"name": "gnt_view", "width": 16, "num_blocks": 2},
}
"""Small parts for a family built with the contract kit's ``kit_parts`` (``parts=KIT_PARTS``): each family takes those it
declares, resunet_fpn as its extractor."""

PART_OPTIONS = {"feature_extractor": "model.feature_extractor.", "field_aggregator": "model.field_aggregator."}
"""The options TINY_MODEL and TINY_CLI give the parts GNT builds (mounted under the model)."""


def for_parts(overrides: list[str], *parts: str) -> list[str]:
    """``overrides`` without the options of the parts a family does not build (``parts``: the kinds it builds), which
    have no place under its model."""
    dropped = tuple(prefix for kind, prefix in PART_OPTIONS.items() if kind not in parts)
    return [o for o in overrides if not o.startswith(dropped)]


def gpnerf(*args, cwd):
    """``python -m gpnerf_core <args>`` in ``cwd``, with its own scene cache and no entry-point plugins."""
    env = dict(os.environ, GPNERF_CACHE=str(cwd / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def child_pids(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid`` (Linux /proc): a launcher's workers, a command's trials."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                found.append(int(entry))
    return found


def in_process(*argv: str) -> int:
    """A command through the command line in this process (no interpreter start-up; a test can replace a writer the
    command uses); its exit code."""
    try:
        return cli_main(list(argv))
    except SystemExit as stop:  # a Hydra job exits through sys.exit
        return int(stop.code)
