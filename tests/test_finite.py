"""``all_finite`` answers as ``torch.isfinite(x).all()`` does, wherever the bad value sits and whatever the layout."""

import pytest
import torch

from gpnerf_core.runtime.finite import all_finite


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_one_bad_value_anywhere_is_found(dtype, bad):
    values = torch.randn(3, 5, 7, 11, generator=torch.Generator().manual_seed(0)).to(dtype)
    assert all_finite(values) and all_finite(values.transpose(1, 3)) and all_finite(values[:, ::2])
    for position in (0, 1, 17, 400, values.numel() - 1):
        damaged = values.clone().view(-1)
        damaged[position] = bad
        damaged = damaged.view_as(values)
        assert not all_finite(damaged) and not all_finite(damaged.transpose(1, 3))
        assert all_finite(damaged) == bool(torch.isfinite(damaged).all())


def test_all_nan_mixed_and_edge_tensors():
    assert not all_finite(torch.full((4,), float("nan")))
    assert not all_finite(torch.tensor([float("inf"), -float("inf")]))
    assert not all_finite(torch.tensor(float("nan")))  # a 0-d loss term
    assert all_finite(torch.tensor(3.0)) and all_finite(torch.empty(0)) and all_finite(torch.empty(2, 0, 3))
    assert all_finite(torch.arange(5)) and all_finite(torch.zeros(3, dtype=torch.bool))  # integers are finite
    big = torch.finfo(torch.float32).max
    assert all_finite(torch.tensor([big, -big]))
