"""The compared methods' families (``+experiment=baselines/<name>``) are trained, evaluated, rendered, fine-tuned and
stressed by the unchanged commands: a tiny run of each (two steps, a 32 x 48 layout), its metrics and one rendered frame
of its checkpoint; for each field (Semantic-Ray's, MVSNeRF's) also two fine-tuning steps on the unseen layout and its
stress at the fewest source views and the largest camera offset. ``neuray`` is ``semantic_ray``'s code without the
CRA: the contract kit and tests/families cover it."""

import json
from pathlib import Path

import pytest

from pipeline_check import TINY_CLI, for_parts, in_process

FAMILIES = {
    "semantic_ray": ["model.fine_samples=4"],
    "mvsnerf": ["model.num_planes=8", "model.coarse_samples=8", "model.fine_samples=0"],  # its own extractor
    "semantic_ray_unet": ["model.fine_samples=4"],  # GP-NeRF's decoding on Semantic-Ray's field
    # GP-NeRF's decoding on MVSNeRF's field: resunet_fpn (TINY_CLI's model.feature_extractor.* apply), one pass
    "mvsnerf_unet": ["model.num_planes=8", "model.coarse_samples=8", "model.fine_samples=0"],
    # MVSplat's Gaussians, label rendering and GP-NeRF's decoding: whole images, a tiny cost volume
    "mvsplat": ["model.feature_dim=8", "model.transformer_layers=1", "model.depth_candidates=4",
                "model.cost_unet_dim=4", "model.depth_unet_dim=4", "model.unet_levels=2", "model.sh_degree=1"],
    "mvsplat_unet": ["model.feature_dim=8", "model.transformer_layers=1", "model.depth_candidates=4",
                     "model.cost_unet_dim=4", "model.depth_unet_dim=4", "model.unet_levels=2", "model.sh_degree=1"],
}
RAY_MARCHING = ("model.coarse_samples", "model.fine_samples")
"""TINY_CLI keys of the ray-marching families' (a rasterizing family has no samples)."""


@pytest.fixture(scope="module")
def trained(request, tmp_path_factory):
    """The family trained 2 steps by ``run``: (name, run folder)."""
    name, out = request.param, tmp_path_factory.mktemp(request.param) / "run"
    tiny = for_parts(TINY_CLI, "feature_extractor")  # GNT's aggregators are no other family's parts
    if name == "mvsnerf":  # its own extractor (mvsnet), which has no resunet_fpn options
        tiny = for_parts(TINY_CLI)
    if name.startswith("mvsplat"):
        tiny = [o for o in tiny if not o.startswith(RAY_MARCHING)]
    assert in_process("run", f"+experiment=baselines/{name}", *tiny, *FAMILIES[name], "train.steps=2",
                      f"out_dir={out}") == 0
    return name, out


@pytest.mark.parametrize("trained", sorted(FAMILIES), indirect=True)
def test_run_trains_and_scores_the_family(trained):
    name, out = trained
    metrics = json.loads((out / "metrics.json").read_text())
    assert json.loads((out / "plugins.json").read_text())["used"]["model"]["name"] == name.removesuffix("_unet")
    for split in ("train_heldout", "unseen"):
        assert 0.0 <= metrics["eval"][split]["miou/image_mean_present"] <= 1.0
        assert metrics["eval"][split]["psnr/clamped"] > 0


@pytest.mark.parametrize("trained", sorted(FAMILIES), indirect=True)
def test_render_writes_a_frame_of_its_checkpoint(trained, tmp_path):
    name, out = trained
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    assert in_process("render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}") == 0
    written = json.loads((tmp_path / "video" / "render.json").read_text())
    assert written["frames"] == 1 and Path(tmp_path / "video" / "trajectory.gif").is_file()


@pytest.mark.parametrize("trained", ["mvsnerf", "semantic_ray", "mvsplat_unet"], indirect=True)
def test_finetune_and_stress_take_its_checkpoint(trained, tmp_path):
    name, out = trained
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    assert in_process("finetune", f"checkpoint={checkpoint}", "dataset.scenes=[unseen_00]", "train.steps=2",
                      "finetune.points=2", "threads=1", f"out_dir={tmp_path / 'tuned'}") == 0
    tuned = json.loads((tmp_path / "tuned" / "metrics.json").read_text())
    assert json.loads((tmp_path / "tuned" / "plugins.json").read_text())["used"]["model"]["name"] == \
        name.removesuffix("_unet")
    assert [point["step"] for point in tuned["finetune"]["curve"]] == [0, 2]
    assert in_process("stress", str(out), "--quick", "--cases", "source_views,translation_noise", "--threads", "1",
                      "--out", str(tmp_path / "stress")) == 0
    results = json.loads((tmp_path / "stress" / "stress.json").read_text())
    assert "source_views" in json.dumps(results) and "translation_noise" in json.dumps(results)


@pytest.mark.parametrize("trained", ["semantic_ray"], indirect=True)
def test_another_family_for_its_checkpoint_is_refused_naming_the_trained_one(trained, tmp_path, capsys):
    _, out = trained
    checkpoint = next((out / "checkpoints").glob("*.pt"))
    assert in_process("eval", f"checkpoint={checkpoint}", "model=gnt", f"out_dir={tmp_path / 'eval'}") == 2
    err = capsys.readouterr().err
    assert f"model=gnt: checkpoint {checkpoint} holds a trained model 'semantic_ray'; eval takes its model family from " \
           "the checkpoint: drop model=..." in err
    assert not (tmp_path / "eval").exists()


def test_mvsplat_with_the_instance_head_trains_and_is_scored_by_instance_ap(tmp_path):
    tiny = [o for o in for_parts(TINY_CLI, "feature_extractor") if not o.startswith(RAY_MARCHING)]
    assert in_process("run", "model=mvsplat", "+head=instance", "+loss=instance", *tiny, *FAMILIES["mvsplat"],
                      "train.steps=2", f"out_dir={tmp_path / 'run'}") == 0
    held_out = json.loads((tmp_path / "run" / "metrics.json").read_text())["eval"]["train_heldout"]
    assert 0.0 <= held_out["instance/ap_matched@0.75"] <= 1.0 and "miou/image_mean_present" not in held_out
