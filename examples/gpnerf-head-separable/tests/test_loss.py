"""The dice loss set keeps its base set's terms and adds a Dice term that ranks predictions correctly."""

import pytest
import torch

from gpnerf_core import get_registry
from gpnerf_core.testing.inputs import loss_inputs
from gpnerf_head_separable.loss import DiceLossSet, soft_dice


def test_terms_are_the_base_sets_plus_dice():
    loss = DiceLossSet(base="dgs", dice_weight=0.5, smooth=1.0)
    inputs = loss_inputs(semantics=True, sample_semantics=True)
    terms = loss(inputs)
    base = get_registry().build("loss", {"name": "dgs"})(inputs)
    assert set(terms) == set(base) | {"dice"}
    assert all(torch.equal(terms[name], value) for name, value in base.items())
    assert loss.needs_semantics and loss.needs_sample_semantics


def test_dice_alone_needs_no_sample_semantics():
    loss = DiceLossSet(base="", dice_weight=1.0, smooth=1.0)
    assert loss.needs_semantics and not loss.needs_sample_semantics
    assert set(loss(loss_inputs(semantics=True, sample_semantics=False))) == {"dice"}


def test_dice_is_near_0_for_a_right_prediction_and_near_1_for_a_wrong_one():
    labels = torch.randint(0, 4, (1, 6, 7))
    labels[0, 0, 0] = 255
    right = torch.nn.functional.one_hot(labels.clamp(max=3), 4).permute(0, 3, 1, 2).float() * 50
    wrong = right.roll(1, dims=1)
    assert soft_dice(right, labels, 255, smooth=1e-3) < 0.01
    assert soft_dice(wrong, labels, 255, smooth=1e-3) > 0.99


def test_a_base_that_includes_itself_is_refused():
    with pytest.raises(Exception, match="would include itself"):
        DiceLossSet(base="dice", dice_weight=0.5, smooth=1.0)
