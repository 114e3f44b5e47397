"""A/B of the transformers' dropout in one process: ``F.dropout`` against the word-based mask (the current one),
alternated over training steps of one model, so both see the same machine state.

    .venv/bin/python examples/ab_dropout.py [bench size, default small] [rounds, default 4]
"""

import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

import gpnerf_plugins.transformers.common as common
import gpnerf_plugins.transformers.ray_transformer as ray_transformer
import gpnerf_plugins.transformers.view_transformer as view_transformer
from gpnerf_core.bench.sizes import get_size, variant_overrides
from gpnerf_core.build import build_components
from gpnerf_core.config import compose
from gpnerf_core.distributed import Distributed
from gpnerf_core.training.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer


def bernoulli_dropout(x, p, training):
    return F.dropout(x, p, training=True) if training and p > 0 else x


def use(dropout):
    common.maybe_dropout = ray_transformer.maybe_dropout = view_transformer.maybe_dropout = dropout


def main(size: str = "small", rounds: int = 4) -> None:
    cfg = compose(variant_overrides(get_size(size), "gpnerf", []))
    word_dropout = common.maybe_dropout
    variants = {"F.dropout": bernoulli_dropout, "word mask": word_dropout}
    with tempfile.TemporaryDirectory() as folder:
        trainer = Trainer(cfg, build_components(cfg), dist=Distributed.single(torch.device("cpu")),
                          run_dir=Path(folder), record=RunRecord(config_yaml="", overrides=(), components={}))
        trainer.model.train()
        for dropout in variants.values():  # warm-up
            use(dropout)
            trainer.train_step()
        times = {name: [] for name in variants}
        for _ in range(rounds):
            for name, dropout in variants.items():
                use(dropout)
                started = time.perf_counter()
                trainer.train_step()
                times[name].append(time.perf_counter() - started)
    print(f"{size}: dropout {cfg.field_aggregator.dropout}, {cfg.train.rays} rays, {torch.get_num_threads()} threads")
    for name, values in times.items():
        print(f"{name}: step min {min(values):.2f} s, median {statistics.median(values):.2f} s")


if __name__ == "__main__":
    main(*(sys.argv[1:2] or ["small"]), *(int(a) for a in sys.argv[2:3]))
