"""Learning-rate schedules: warm-up, exponential and cosine decay."""

import math

import pytest

from gpnerf_core.errors import ConfigError
from gpnerf_core.training.schedule import lr_factor


def test_exponential_without_warmup_is_the_rate_per_decay_steps():
    factor = lr_factor("exponential", steps=600, warmup_steps=0, decay_rate=0.5, decay_steps=600)
    assert factor(0) == 1.0 and factor(300) == pytest.approx(math.sqrt(0.5)) and factor(600) == pytest.approx(0.5)


def test_warmup_rises_linearly_then_cosine_reaches_zero_at_the_last_step():
    factor = lr_factor("cosine", steps=100, warmup_steps=10, decay_rate=1.0, decay_steps=1)
    assert [factor(s) for s in (0, 4, 9)] == pytest.approx([0.1, 0.5, 1.0])
    assert factor(10) == pytest.approx(1.0)
    assert factor(55) == pytest.approx(0.5)
    assert factor(100) == pytest.approx(0.0, abs=1e-12)
    values = [factor(s) for s in range(10, 101)]
    assert all(a >= b for a, b in zip(values, values[1:]))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(schedule="linear"), r"train.lr_schedule='linear': expected one of exponential, cosine"),
        (dict(warmup_steps=-1), r"train.warmup_steps=-1"),
        (dict(decay_rate=0.0), r"train.lr_decay_rate must be in \(0, 1\]"),
    ],
)
def test_bad_values_are_named(kwargs, message):
    options = dict(schedule="cosine", steps=10, warmup_steps=0, decay_rate=0.5, decay_steps=10) | kwargs
    with pytest.raises(ConfigError, match=message):
        lr_factor(options.pop("schedule"), **options)
