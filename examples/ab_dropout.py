"""A/B of the transformers' dropout in one process: ``F.dropout`` (a Bernoulli draw per element) against the word-based
mask the ``gpnerf_plugins`` transformers use, alternated over training steps of one model
(``gpnerf_core.alternate``). The ``small`` and ``paper`` sizes train with dropout 0.1, ``demo`` with none.

    python examples/ab_dropout.py [size=small] [rounds=4] [threads=2] [overrides...]
"""

import sys
import tempfile
from pathlib import Path

import torch
import torch.nn.functional as F

import gpnerf_plugins.transformers.common as common
import gpnerf_plugins.transformers.ray_transformer as ray_transformer
import gpnerf_plugins.transformers.view_transformer as view_transformer
from gpnerf_core import alternate, make_trainer, timing_lines


def bernoulli_dropout(x: torch.Tensor, p: float, training: bool) -> torch.Tensor:
    return F.dropout(x, p, training=True) if training and p > 0 else x


def use(dropout):
    def apply(trainer):
        common.maybe_dropout = ray_transformer.maybe_dropout = view_transformer.maybe_dropout = dropout
    return apply


def main(argv: list[str]) -> None:
    settings = {"size": "small", "rounds": "4", "threads": "2"}
    overrides = [a for a in argv if a.partition("=")[0] not in settings]
    settings.update(a.split("=", 1) for a in argv if a.partition("=")[0] in settings)
    torch.set_num_threads(int(settings["threads"]))
    variants = {"F.dropout": use(bernoulli_dropout), "word mask": use(common.maybe_dropout)}
    with tempfile.TemporaryDirectory() as folder:
        trainer = make_trainer(settings["size"], overrides, Path(folder))
        times, warm_up = alternate(trainer, variants, int(settings["rounds"]))
    print(f"dropout A/B, size={settings['size']}, {torch.get_num_threads()} threads:")
    print("\n".join(timing_lines(times, warm_up)))


if __name__ == "__main__":
    main(sys.argv[1:])
