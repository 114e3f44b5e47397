"""What the separable head adds over a per-pixel classifier: context from the coarse levels."""

import pytest
import torch

from gpnerf_core import ConfigError
from gpnerf_head_separable.head import SeparableHead

SIZES = dict(in_dim=16, in_levels=4, num_outputs=5, channels=8, kernel_size=3, norm_groups=2)


def test_a_change_in_one_corner_reaches_the_opposite_corner():
    torch.manual_seed(0)
    head = SeparableHead(**SIZES).eval()
    features = torch.randn(1, 16, 16, 16)
    changed = features.clone()
    changed[:, :, :2, :2] += 5.0  # top-left, every level
    with torch.no_grad():
        before, after = head(features, (16, 16)).logits, head(changed, (16, 16)).logits
    assert not torch.allclose(before[..., -1, -1], after[..., -1, -1])  # bottom-right moved: context


@pytest.mark.parametrize("change, message", [
    (dict(norm_groups=3), "head.norm_groups=3 does not divide head.channels=8"),
    (dict(kernel_size=4), "head.kernel_size=4: expected an odd positive size"),
    (dict(in_dim=15), "in_dim=15 for in_levels=4"),
])
def test_bad_sizes_are_refused_in_one_line(change, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        SeparableHead(**{**SIZES, **change})
