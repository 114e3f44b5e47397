"""DM-NeRF (``model=dm_nerf``, per scene): the object field reads detached trunk features and is composited with
detached weights, so instance losses never shape geometry; slot probabilities are per-slot sigmoids after compositing;
the matched object loss and the 3D emptiness penalty; a tiny run scored by instance AP, and one rendered frame."""

from __future__ import annotations

import json

import pytest
import torch

from gpnerf_core.cli import main as cli_main
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation.instances import slot_predictions
from gpnerf_core.geometry import rays_through_pixels
from gpnerf_plugins.families.dm_nerf.model import DMNeRF
from gpnerf_plugins.losses.dm_nerf import DMNeRFLossSet, emptiness_penalty, gaussian_weight
from gpnerf_plugins.losses.instance import matched_instance_loss
from pipeline_check import TINY_CLI, for_parts

SMALL = dict(slots=4, coarse_samples=8, fine_samples=4, width=16, depth=4, skip=1, position_scale=1.0,
             position_frequencies=3, direction_frequencies=2, density_noise=0.0, inverse_depth=False)


def _rays(count: int = 6):
    pixels = torch.rand(count, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor([47.0, 31.0])
    intrinsics = torch.tensor([[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])
    return rays_through_pixels(pixels, intrinsics, torch.eye(4), 0.2, 6.0)


def test_instance_gradients_never_reach_the_geometry():
    model = DMNeRF(**SMALL)
    for field in (model.coarse, model.fine):
        field.density.bias.data.fill_(1.0)
    coarse, fine = model.render_rays(_rays(), True, torch.Generator().manual_seed(1), per_sample=True)
    (fine.logits.sum() + fine.sample_semantic.sum() + coarse.logits.sum()).backward()
    geometry = [p for name, p in model.named_parameters() if ".branch." not in name]
    assert all(p.grad is None or not p.grad.any() for p in geometry)
    assert all(p.grad is not None and p.grad.any() for p in model.fine.branch.parameters())
    assert coarse.logits.shape == (6, 5) and fine.sample_semantic.shape == (6, 12, 5)
    assert torch.allclose(fine.logits, torch.einsum("rs,rsk->rk", fine.weights.detach(), fine.sample_semantic))


def test_slots_are_each_their_own_sigmoid_after_compositing():
    output = DMNeRF(**SMALL).semantic_output
    assert (output.slots, output.num_outputs, output.slot_activation) == (4, 5, "sigmoid")
    logits = torch.tensor([[3.0, -1.0], [2.5, 4.0], [-5.0, -5.0], [-5.0, -5.0], [9.0, 9.0]])[:, :, None]  # [K + 1, 2, 1]
    slots, confidence = slot_predictions(logits, "sigmoid")
    assert slots[:, 0].tolist() == [0, 1]  # the empty slot (last) is dropped even where it is the largest
    assert confidence[0] == pytest.approx(torch.sigmoid(torch.tensor(3.0)).item())
    assert confidence[1] == pytest.approx(torch.sigmoid(torch.tensor(4.0)).item())  # not renormalised over slots
    assert slot_predictions(logits, "softmax")[1][1] < confidence[1]


def test_the_matched_object_loss_is_low_for_the_right_slots_and_names_too_few():
    ids = torch.tensor([7, 7, 3, 3, 3, 9])
    right = torch.full((3, 6), -8.0)
    for slot, instance in enumerate((3, 7, 9)):
        right[slot, ids == instance] = 8.0
    good = matched_instance_loss(torch.nn.functional.logsigmoid(right), ids, "model", "model.slots")
    bad = matched_instance_loss(torch.nn.functional.logsigmoid(-right), ids, "model", "model.slots")
    assert sum(good.values()) < 0.01 < sum(bad.values())
    with pytest.raises(ConfigError, match=r"3 instance ids .* the model has 2 slots; set model.slots >= 3"):
        matched_instance_loss(torch.zeros(2, 6), ids, "model", "model.slots")


def test_the_emptiness_penalty_empties_the_front_and_fills_the_surface():
    depths = torch.tensor([[1.0, 2.0, 3.0]])
    logits = torch.zeros(1, 3, 3, requires_grad=True)  # K + 1 = 3 outputs, every sigmoid at 0.5
    penalty = emptiness_penalty(logits, depths, torch.tensor([2.0]), tolerance=0.05, sigma=0.05)
    penalty.backward()
    grad = logits.grad[0]
    assert grad[0, :2].gt(0).all() and grad[0, 2] < 0  # in front: objects down, empty up
    assert grad[1, 2] > 0 and not grad[1, :2].any()  # at the surface: the empty slot down only
    assert not grad[2].any()  # behind the surface: no term
    assert gaussian_weight(torch.tensor(0.0), 0.05) == pytest.approx(1 / (0.4 * (2 * torch.pi) ** 0.5))
    for bad, message in (({"empty_sigma": 0}, "loss.empty_sigma=0: expected metres > 0"),
                         ({"rgb_weight": 0, "object_weight": 0, "empty_weight": 0}, "every loss weight")):
        with pytest.raises(ConfigError, match=message):
            DMNeRFLossSet(**bad)
    assert DMNeRFLossSet(empty_weight=0).needs_sample_semantics is False


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    out = tmp_path_factory.mktemp("dm_nerf") / "run"
    argv = ["run", "+experiment=baselines/dm_nerf", *for_parts(TINY_CLI), "model.width=16", "model.depth=3", "model.skip=1",
            "model.coarse_samples=4", "model.fine_samples=4", "train.rays=16", "dataset.scenes=[layout_00]",
            "train.steps=2", "eval.chunk_rays=512", f"out_dir={out}"]
    assert cli_main(argv) == 0
    return out


def test_run_fits_one_scene_and_scores_its_instances(fitted):
    metrics = json.loads((fitted / "metrics.json").read_text())["eval"]["train_heldout"]
    for key in ("instance/ap_matched@0.75", "instance/coco_mask_ap"):
        assert 0.0 <= metrics[key] <= 1.0
    assert "miou/image_mean_present" not in metrics


def test_render_draws_the_instances_of_a_frame(fitted, tmp_path):
    checkpoint = next((fitted / "checkpoints").glob("*.pt"))
    assert cli_main(["render", f"checkpoint={checkpoint}", "render.frames=1", f"out_dir={tmp_path / 'video'}"]) == 0
    assert json.loads((tmp_path / "video" / "render.json").read_text())["frames"] == 1


def test_too_few_slots_for_the_scene_names_dm_nerfs_own_key():
    from gpnerf_core.config.compose import compose
    from gpnerf_core.engine.validation import check_data
    from gpnerf_core.model.build import build_components
    from pipeline_check import TINY_SCENES

    cfg = compose(["+experiment=baselines/dm_nerf", *TINY_SCENES, "dataset.scenes=[layout_00]", "model.slots=1"])
    with pytest.raises(ConfigError, match=r"instance ids \(background included\) but model.slots=1; set model.slots >= "):
        check_data(cfg, build_components(cfg), training=True)
