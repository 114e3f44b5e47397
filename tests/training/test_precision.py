"""train.precision=bf16: the forward pass under bfloat16 autocast stays within stated bounds of float32 on CPU.

Bounds, at the CPU-scale default model (96x128 images, untrained weights): every loss term within 10% relative,
rendered colour within 0.03 mean absolute error, rendered semantic features within 8% relative mean absolute error,
and at least 85% of the head's per-pixel classes unchanged. bfloat16 keeps 8 mantissa bits (0.4% per rounding).
"""

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.device import autocast
from gpnerf_core.errors import ConfigError
from pipeline_check import make_trainer


@pytest.fixture(scope="module")
def both_precisions(tmp_path_factory):
    root = tmp_path_factory.mktemp("bf16")
    cfg = compose(["+head=unet", "+loss=dgs", "threads=1", "train.rays=128", f"dataset.root={root / 'scenes'}",
                   "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=8"])
    torch.manual_seed(0)
    trainer = make_trainer(cfg, root / "run")
    batch = trainer.sampler.next_batch()
    with torch.no_grad():
        fp32 = trainer.model(batch, semantics=True, sample_semantics=True)
        fp32_terms = trainer._loss_terms(batch, fp32)
        with autocast(torch.device("cpu"), "bf16"):
            bf16 = trainer.model(batch, semantics=True, sample_semantics=True)
            bf16_terms = trainer._loss_terms(batch, bf16)
    return (fp32, fp32_terms), (bf16, bf16_terms)


def test_bf16_loss_terms_within_ten_percent(both_precisions):
    (_, fp32_terms), (_, bf16_terms) = both_precisions
    for name, value in fp32_terms.items():
        assert bf16_terms[name].dtype == torch.float32  # terms are reduced in float32
        low, high = bf16_terms[name].item(), value.item()
        assert abs(low - high) <= 0.10 * abs(high), name


def test_bf16_rendered_outputs_within_bounds(both_precisions):
    (fp32, _), (bf16, _) = both_precisions
    a, b = fp32.views[0], bf16.views[0]
    assert b.fine.rgb.dtype == torch.bfloat16  # autocast is really on
    assert float((a.fine.rgb - b.fine.rgb.float()).abs().mean()) < 0.03
    semantic_error = (a.fine.semantic - b.fine.semantic.float()).abs().mean() / a.fine.semantic.abs().mean()
    assert float(semantic_error) < 0.08
    assert float((a.logits.argmax(1) == b.logits.argmax(1)).float().mean()) > 0.85


def test_bf16_training_step_keeps_float32_weights(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", "train.precision=bf16", "threads=1", f"dataset.root={tmp_path / 's'}",
                   "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6",
                   "dataset.eval_every=3", "dataset.height=32", "dataset.width=48", "train.rays=16",
                   "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=8",
                   "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.num_source_views=2",
                   "train.steps=2", "train.log_every=1"])
    trainer = make_trainer(cfg, tmp_path / "run")
    result = trainer.fit(progress=False)
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in result.history)
    assert all(p.dtype == torch.float32 for p in trainer.model.parameters())


def test_unknown_precision_is_refused():
    with pytest.raises(ConfigError, match="train.precision='fp16': expected one of fp32, bf16"):
        autocast(torch.device("cpu"), "fp16")
