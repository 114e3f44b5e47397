"""Gaussian Grouping's own parts: the 2D identity loss, the 3D regulariser, the Gaussians' slots, bad ids."""

import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from gpnerf_core import DataError, ImageOutput
from gpnerf_core.testing.inputs import model_scene
from gpnerf_gaussian_grouping.model import GaussianGrouping
from gpnerf_gaussian_grouping.plugin import build_gaussian_grouping

SLOTS = 4


class NoParts:
    num_classes = 3

    def configured(self, kind):
        return False


def grouping(**options) -> GaussianGrouping:
    model = build_gaussian_grouping(parts=NoParts(), identity_dim=4, slots=SLOTS, init_points=120, sh_degree=1,
                                    reg3d_sample_size=30, **options)
    model.hooks.initialise(model_scene())
    return model


def test_the_identity_loss_is_the_cross_entropy_over_ln_k_at_the_kept_pixels():
    torch.manual_seed(0)
    model = grouping()
    scores, ids = torch.randn(1, SLOTS + 1, 6, 5), torch.randint(0, SLOTS, (6, 5))
    valid = torch.rand(6, 5) > 0.3
    view = SimpleNamespace(instances=ids, valid=valid, scene="s", frame=0)
    output = ImageOutput(rgb=torch.zeros(6, 5, 3), depth=None, scores=scores)
    expected = F.cross_entropy(scores, ids[None], reduction="none")[0][valid].mean() / math.log(SLOTS + 1)
    assert torch.allclose(model.identity_loss(view, output), expected)


def test_an_id_without_a_class_is_refused_naming_the_frame_and_the_key():
    model = grouping()
    view = SimpleNamespace(instances=torch.full((2, 2), SLOTS), valid=None, scene="room", frame=7)
    output = ImageOutput(rgb=torch.zeros(2, 2, 3), depth=None, scores=torch.zeros(1, SLOTS + 1, 2, 2))
    with pytest.raises(DataError, match=r"scene 'room' frame 7 has instance id 4; model.slots=4 takes ids 0 to 3: "
                                        r"set model.slots > 4"):
        model.identity_loss(view, output)


def test_the_3d_regulariser_is_zero_for_alike_neighbours_and_positive_otherwise():
    model = grouping()
    with torch.no_grad():
        model.gaussians.identity.zero_()
    assert float(model.neighbour_kl(seed=1).detach()) == pytest.approx(0.0, abs=1e-7)
    with torch.no_grad():
        model.gaussians.identity.normal_()
    kl = model.neighbour_kl(seed=1)
    assert float(kl.detach()) > 0 and torch.equal(kl, model.neighbour_kl(seed=1))  # the same draw for the same seed
    kl.backward()
    assert model.gaussians.identity.grad.abs().sum() > 0 and model.gaussians.means.grad is None  # centres detached


def test_each_gaussian_is_labelled_with_its_slot_and_minus_one_for_no_instance():
    model = grouping()
    with torch.no_grad():
        model.classifier.weight.zero_()
        model.classifier.bias.copy_(torch.tensor([0.0, 0.0, 5.0, 0.0, 9.0]))  # the "no instance" output wins
        labels = model.scene_gaussians(None, near=0.1, far=10.0).labels
        assert bool((labels == -1).all())
        model.classifier.bias[-1] = -9.0
        assert bool((model.scene_gaussians(None, near=0.1, far=10.0).labels == 2).all())


def test_a_head_is_refused_naming_it():
    class WithHead(NoParts):
        def configured(self, kind):
            return kind == "head"

        def name(self, kind):
            return "unet"

    from gpnerf_core import ConfigError

    with pytest.raises(ConfigError, match=r"drop \+head=unet"):
        build_gaussian_grouping(parts=WithHead())
