"""Weight average (``train.ema_decay``): the update rule, exact resume, what evaluation and checkpoints use."""

from pathlib import Path

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.checkpoint import evaluation_weights, read_checkpoint
from gpnerf_core.training.weight_average import WeightAverage
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer


def tiny_cfg(tmp_path, *extra):
    root = f"dataset.root={tmp_path / 'scenes'}"
    return compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, root, *extra])


def test_average_follows_the_decay_schedule_and_copies_integer_buffers():
    model = torch.nn.BatchNorm1d(2)
    average = WeightAverage(model, decay=0.9)
    values = []
    for step in range(1, 31):
        with torch.no_grad():
            model.weight.fill_(float(step))
        model.num_batches_tracked.fill_(step)
        average.update(model)
        values.append(float(step))
    expected = 1.0  # the initial weight
    for t, value in enumerate(values):
        d = min(0.9, (1 + t) / (10 + t))
        expected = d * expected + (1 - d) * value
    assert average.average["weight"][0].item() == pytest.approx(expected, rel=1e-6)
    assert int(average.average["num_batches_tracked"]) == 30
    assert values[-1] > expected > values[-15]  # lags behind the weights, by about 1 / (1 - d) steps


def test_swapped_in_restores_the_trained_weights():
    model = torch.nn.Linear(3, 2)
    average = WeightAverage(model, decay=0.5)
    with torch.no_grad():
        model.weight.add_(1.0)
    average.update(model)
    trained = model.weight.detach().clone()
    with average.swapped_in(model):
        assert torch.equal(model.weight, average.average["weight"]) and not torch.equal(model.weight, trained)
    assert torch.equal(model.weight, trained)


def test_training_is_unchanged_and_checkpoints_hold_both_weight_sets(tmp_path):
    torch.manual_seed(0)
    plain = make_trainer(tiny_cfg(tmp_path, "train.steps=3"), tmp_path / "a")
    plain.fit(progress=False)
    torch.manual_seed(0)
    averaged = make_trainer(tiny_cfg(tmp_path, "train.steps=3", "train.ema_decay=0.9"), tmp_path / "b")
    result = averaged.fit(progress=False)
    for (name, a), (_, b) in zip(plain.model.state_dict().items(), averaged.model.state_dict().items()):
        assert torch.equal(a, b), name
    state = read_checkpoint(result.checkpoint)
    weights, which = evaluation_weights(state)
    assert which == "average" and state["weight_average"]["updates"] == 3
    assert any(not torch.equal(weights[key], state["model"][key]) for key in weights)
    assert evaluation_weights(state, "trained")[1] == "trained"
    with averaged.evaluation_weights() as evaluated:
        assert evaluated == "average"
        assert torch.equal(averaged.model.state_dict()[next(iter(weights))], weights[next(iter(weights))])
    plain_state = read_checkpoint(plain.fit(progress=False).checkpoint)
    assert plain_state["weight_average"] is None and evaluation_weights(plain_state)[1] == "trained"
    assert all(h["grad_norm"] > 0 for h in result.history)


def test_resume_continues_the_average_exactly(tmp_path):
    torch.manual_seed(0)
    straight = make_trainer(tiny_cfg(tmp_path, "train.steps=4", "train.ema_decay=0.9"), tmp_path / "a")
    straight.fit(progress=False)
    torch.manual_seed(0)
    make_trainer(tiny_cfg(tmp_path, "train.steps=2", "train.ema_decay=0.9"), tmp_path / "b").fit(progress=False)
    checkpoint = Path(tmp_path / "b" / "checkpoints" / "step_0000002.pt")
    resumed = make_trainer(
        tiny_cfg(tmp_path, "train.steps=4", "train.ema_decay=0.9", f"train.resume={checkpoint}"), tmp_path / "c"
    )
    resumed.fit(progress=False)
    for key, value in straight.average.average.items():
        assert torch.equal(value, resumed.average.average[key]), key
    assert resumed.average.updates == 4


def test_resume_with_an_average_from_a_checkpoint_without_one_is_refused(tmp_path):
    trainer = make_trainer(tiny_cfg(tmp_path, "train.steps=1"), tmp_path / "a")
    checkpoint = trainer.fit(progress=False).checkpoint
    with pytest.raises(ConfigError, match=r"train.ema_decay=0.9 but the checkpoint kept no weight average"):
        make_trainer(tiny_cfg(tmp_path, "train.steps=2", "train.ema_decay=0.9", f"train.resume={checkpoint}"),
                     tmp_path / "b")


def test_unknown_weight_choice_is_refused():
    with pytest.raises(ConfigError, match=r"eval.weights='best': expected one of average, trained"):
        evaluation_weights({"model": {}, "weight_average": None}, "best")
