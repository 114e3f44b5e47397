"""Training loop behaviour: non-finite losses stop training, resume is exact, parameter groups get their rates."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from gpnerf_core.build import build_components
from gpnerf_core.cli import config_dir
from gpnerf_core.config import register_schema
from gpnerf_core.errors import NonFiniteError
from gpnerf_core.interfaces import LossSet
from gpnerf_core.registry import get_registry
from gpnerf_core.training.trainer import Trainer

TINY = [
    "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.height=32", "dataset.width=48", "feature_extractor.widths=[8,8,8,16]", "feature_extractor.fpn_channels=4",
    "field_aggregator.width=16", "field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "train.log_every=1", "threads=1",
]


def tiny_cfg(tmp_path, *extra):
    get_registry()
    register_schema()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return compose(
            config_name="config",
            overrides=["+head=unet", "+loss=dgs", *TINY, f"dataset.root={tmp_path / 'scenes'}", *extra],
        )


class PoisonedLoss(LossSet):
    """Returns a NaN term on its second call."""

    needs_semantics = False

    def __init__(self):
        super().__init__()
        self.calls = 0

    def forward(self, inputs):
        self.calls += 1
        value = (inputs.coarse.rgb - inputs.target_rgb).pow(2).mean()
        return {"rgb": value, "sd": value * (float("nan") if self.calls == 2 else 0.0)}


def test_nan_loss_stops_training_naming_step_and_term(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.steps=3")
    components = build_components(cfg)
    components.loss = PoisonedLoss()
    trainer = Trainer(cfg, components, torch.device("cpu"), tmp_path / "run", "")
    with pytest.raises(NonFiniteError, match=r"step 1: loss term 'sd' is nan"):
        trainer.fit(progress=False)
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_learning_rate_groups(tmp_path):
    cfg = tiny_cfg(tmp_path, "train.lr.feature_extractor=0.1", "train.lr.transformer=0.2", "train.lr.head=0.3")
    trainer = Trainer(cfg, build_components(cfg), torch.device("cpu"), tmp_path / "run", "")
    rates = {group["name"]: group["lr"] for group in trainer.optimizer.param_groups}
    assert rates == {"feature_extractor": 0.1, "transformer": 0.2, "head": 0.3}
    extractor_params = {id(p) for p in trainer.model.extractor.parameters()}
    assert {id(p) for p in trainer.optimizer.param_groups[0]["params"]} == extractor_params


def test_resume_continues_exactly(tmp_path):
    torch.manual_seed(0)
    cfg = tiny_cfg(tmp_path, "train.steps=4", "train.checkpoint_every=2")
    straight = Trainer(cfg, build_components(cfg), torch.device("cpu"), tmp_path / "a", "")
    straight_result = straight.fit(progress=False)

    torch.manual_seed(0)
    first = Trainer(cfg, build_components(cfg), torch.device("cpu"), tmp_path / "b", "")
    half_cfg = tiny_cfg(tmp_path, "train.steps=2")
    first.cfg = half_cfg
    first.fit(progress=False)
    checkpoint = Path(tmp_path / "b" / "checkpoints" / "step_0000002.pt")

    torch.manual_seed(123)  # resuming must not depend on the state the process happens to be in
    resumed_cfg = tiny_cfg(tmp_path, "train.steps=4", f"train.resume={checkpoint}")
    resumed = Trainer(resumed_cfg, build_components(resumed_cfg), torch.device("cpu"), tmp_path / "c", "")
    resumed_result = resumed.fit(progress=False)
    assert [h["loss"] for h in resumed_result.history] == [h["loss"] for h in straight_result.history]
    for (name, a), (_, b) in zip(straight.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
