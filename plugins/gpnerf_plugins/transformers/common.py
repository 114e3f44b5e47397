"""Building blocks shared by GNT's view and ray transformers: dropout, feed-forward, positional encoding."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gpnerf_core import ConfigError

# GNT's mask value. float16 cannot hold it, so ``masking_value`` clamps it to the dtype's range.
MASK_VALUE = -1e9


def masking_value(dtype: torch.dtype) -> float:
    """The logit written into masked slots: -1e9, or the most negative finite value of a narrower dtype.

    A finite value (never -inf) keeps a softmax over slots that are all masked uniform instead of NaN.
    """
    return max(MASK_VALUE, torch.finfo(dtype).min)


def maybe_dropout(x: Tensor, p: float, training: bool) -> Tensor:
    """Dropout in training with p > 0 (``x * dropout_mask(x, p)``); otherwise ``x`` itself (no kernel call, no copy)."""
    if training and p > 0.0:
        return x * dropout_mask(x, p)
    return x


SHORT_SOFTMAX = 16
"""Below this many elements in the last dimension torch's CPU softmax kernel is the slow one (see ``softmax_last``)."""


def softmax_last(scores: Tensor) -> Tensor:
    """``torch.softmax(scores, dim=-1)``; on CPU without autograd and for a last dimension of fewer than
    ``SHORT_SOFTMAX`` elements (a ray's samples in a one-pass render: 8), the same function in four elementwise
    passes: there torch's kernel costs 5-10x more (``[1024, 4, 8, 8]``, 2 threads: 2.4 ms against 0.4 ms; at 16
    elements and more it is the faster one). The two agree to 1-2 float32 ULPs, not bit for bit, so a training
    step (autograd on) keeps torch's kernel and its numerics.
    """
    if scores.device.type != "cpu" or torch.is_grad_enabled() or scores.shape[-1] >= SHORT_SOFTMAX:
        return torch.softmax(scores, dim=-1)
    exp = (scores - scores.amax(dim=-1, keepdim=True)).exp_()
    return exp.div_(exp.sum(dim=-1, keepdim=True))


LEVELS = 1 << 16
"""A dropout decision is one 16-bit uniform level: p is applied as round(p * 65536) / 65536 (0.1 -> 0.100006)."""


def dropout_mask(x: Tensor, p: float) -> Tensor:
    """The scaled keep-mask of dropout with probability ``p``, shaped and typed like ``x``: ``1 / (1 - p')`` where kept,
    0 where dropped, with ``p' = round(p * 65536) / 65536``.

    ``F.dropout`` draws one Bernoulli number per element (``bernoulli_``: 12-14% of a GNT training step on a CPU); here
    one 64-bit random word from torch's generator on ``x``'s device gives four 16-bit levels, each compared with a
    threshold (about 2.6x faster on a 5-million-element tensor on this CPU). Seeded like ``F.dropout`` (torch's
    global generator), so a run is as reproducible as before; its draws differ from ``F.dropout``'s.
    """
    count = x.numel()
    threshold = min(round(p * LEVELS), LEVELS - 1)
    words = torch.randint(torch.iinfo(torch.int64).min, torch.iinfo(torch.int64).max, ((count + 3) // 4,),
                          dtype=torch.int64, device=x.device)
    levels = words.view(torch.int16)[:count].view(x.shape)  # uniform over [-32768, 32767]
    keep = levels >= threshold - LEVELS // 2
    return keep.to(x.dtype).mul_(LEVELS / (LEVELS - threshold))


def check_dropout(owner: str, p: float) -> None:
    """Raise ConfigError unless ``0 <= p < 1``."""
    if not 0.0 <= p < 1.0:
        raise ConfigError(f"{owner}.dropout must be in [0, 1), got {p}")


def check_positive(owner: str, key: str, value: int) -> None:
    """Raise ConfigError unless ``value`` is a positive int."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{owner}.{key} must be a positive integer, got {value!r}")


def linear_rows(x: Tensor, layer: nn.Linear) -> Tensor:
    """``layer`` applied to the rows of a 2-D ``x [N, in]``, giving a fresh ``[N, out]`` tensor.

    Callers keep tensors 2-D around this so that in-place ops on the result do not modify a view (autograd
    would then copy the whole gradient back through the base). The weight operand's memory layout decides
    which way autograd computes the weight gradient, a GEMM reducing over the N rows; on CPU BLAS that
    reduction is 2-3x faster with the narrower side first, so the transposed weight is made contiguous
    when the layer widens (in < out) and used as a strided view otherwise.
    """
    weight = layer.weight
    mat2 = weight.t().contiguous() if weight.shape[1] < weight.shape[0] else weight.t()
    if layer.bias is None:
        return x @ mat2
    return torch.addmm(layer.bias, x, mat2)


class FeedForward(nn.Module):
    """GNT's position-wise MLP: Linear(D, D*ratio) -> ReLU -> dropout -> Linear(D*ratio, D) -> dropout.

    Parameter names (``fc1``, ``fc2``) match GNT's so its checkpoints load.
    """

    def __init__(self, dim: int, hidden: int, dropout: float) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)
        self.dropout = dropout

    def forward(self, x: Tensor) -> Tensor:
        """``[..., D]`` -> ``[..., D]``."""
        h = linear_rows(x.reshape(-1, x.shape[-1]), self.fc1).relu_()
        h = maybe_dropout(h, self.dropout, self.training)
        out = maybe_dropout(linear_rows(h, self.fc2), self.dropout, self.training)
        return out.view(x.shape)


def encoding_dim(num_frequencies: int, input_dim: int = 3) -> int:
    """Width of ``positional_encoding``: the input plus a sin and a cos per frequency and coordinate."""
    return input_dim * (1 + 2 * num_frequencies)


def positional_encoding(x: Tensor, num_frequencies: int) -> Tensor:
    """NeRF encoding with the input included, in GNT's channel order.

    Args:
        x: ``[..., C]`` coordinates (GNT: raw world points in metres, or unit directions).
        num_frequencies: F; frequencies 2^0 .. 2^(F-1).

    Returns:
        ``[..., C * (1 + 2F)]``: ``x``, then for each frequency f the block ``sin(f x)`` followed by ``cos(f x)``.
    """
    if num_frequencies == 0:
        return x
    freqs = 2.0 ** torch.arange(num_frequencies, device=x.device, dtype=x.dtype)
    scaled = x[..., None, :] * freqs[:, None]  # [..., F, C]
    periodic = torch.stack((scaled.sin(), scaled.cos()), dim=-2)  # [..., F, 2, C]
    return torch.cat((x, periodic.flatten(-3)), dim=-1)
