"""Every tensor the hot path creates follows the model's device (so training runs on CUDA as on the CPU).

On the CPU this is checked by making ``meta`` torch's default device while a training step and a whole-view prediction
run: a factory call without an explicit device (``torch.rand(..., generator=...)``, ``torch.zeros(n)``) would then
make a meta tensor and fail as soon as it met a real one. With a GPU present the same steps also run on CUDA.
"""

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.evaluation.evaluator import evaluate
from gpnerf_core.data.frames import choose_sources
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer


@pytest.fixture
def trainer(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"])
    trainer = make_trainer(cfg, tmp_path / "run")
    for name in ("layout_00", "unseen_00"):
        trainer.frames.scene(name)  # files are read before the device switch; reading is not the hot path
    return trainer


def test_no_factory_in_the_training_step_or_prediction_relies_on_the_default_device(trainer):
    scene = trainer.frames.scene("unseen_00")
    index = scene.eval_frames[0]
    sources = trainer.frames.source_views(scene, choose_sources(trainer.sampler.selector, scene, index, 2, None))
    camera = trainer.frames.camera(scene, trainer.frames.frame(scene, index))
    torch.set_default_device("meta")
    try:
        terms, rays, _ = trainer.train_step()
        prediction = trainer.model.predict(camera, sources, stride=0, chunk_rays=64)
    finally:
        torch.set_default_device("cpu")
    assert terms["loss"].device.type == "cpu" and rays == 16
    assert prediction.rgb.device.type == "cpu" and prediction.logits.device.type == "cpu"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_training_and_evaluation_run_on_cuda(tmp_path):
    # The scene cache, not a fresh root: on a GPU image without pybullet, gpu_check/prepare.sh has rendered this set.
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, "device=cuda", "eval.max_views_per_scene=1"])
    components = build_components(cfg)
    device = Distributed.single(torch.device("cuda"))
    trainer = make_trainer(cfg, tmp_path / "run", dist=device, components=components)
    result = trainer.fit(progress=False)
    assert result.steps == 2 and next(trainer.model.parameters()).device.type == "cuda"
    metrics = evaluate(cfg, components, trainer.frames, tmp_path / "run", device)
    assert metrics["eval"]["unseen"]["count/images"] >= 1
