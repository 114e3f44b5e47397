"""Shared by the dataset tests: train and evaluate a tiny GP-NeRF on any SceneDataset, through the real pipeline."""

from __future__ import annotations

from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from gpnerf_core.build import build_components
from gpnerf_core.cli import config_dir
from gpnerf_core.config import register_schema
from gpnerf_core.evaluation.evaluator import evaluate
from gpnerf_core.registry import get_registry
from gpnerf_core.training.trainer import Trainer

TINY_MODEL = [
    "feature_extractor.widths=[8,8,8,16]", "feature_extractor.fpn_channels=4", "field_aggregator.width=16",
    "field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2",
    "train.rays=16", "train.steps=2", "train.log_every=1", "eval.chunk_rays=256", "eval.save_images=1", "threads=1",
]


def train_and_evaluate(dataset_overrides: list[str], run_dir: Path) -> dict:
    """Compose ``+head=unet +loss=dgs`` with the dataset overrides, train 2 steps, evaluate; returns the metrics."""
    get_registry()
    register_schema()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["+head=unet", "+loss=dgs", *TINY_MODEL, *dataset_overrides])
    torch.manual_seed(0)
    components = build_components(cfg)
    trainer = Trainer(cfg, components, torch.device("cpu"), run_dir, "")
    result = trainer.fit(progress=False)
    assert result.steps == 2 and all(torch.isfinite(torch.tensor(h["loss"])) for h in result.history)
    return evaluate(cfg, components, trainer.views, torch.device("cpu"), run_dir)


def assert_both_splits_scored(metrics: dict, num_classes: int) -> None:
    """Both evaluation splits scored at least one image, with an mIoU in [0, 1] over ``num_classes`` classes."""
    for split in ("train_heldout", "unseen"):
        values = metrics["eval"][split]
        assert values["count/images"] >= 1 and 0.0 <= values["miou/image_mean_present"] <= 1.0
        assert len(values["iou/dataset_per_class"]) == num_classes
