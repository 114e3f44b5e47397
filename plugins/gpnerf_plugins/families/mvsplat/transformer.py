"""MVSplat's multi-view Transformer (from UniMatch/GMFlow, ``backbone/multiview_transformer.py``): the V source views'
1/4 feature maps exchange information by self-attention within each view and cross-attention to the other views, in
windows: each map is cut into ``splits x splits`` windows, every other block shifted by half a window (Swin), so a
token attends to the tokens of its window in its own view (self) and in every other view (cross).

One block: self-attention (q, k, v and merge without bias, LayerNorm on the message, added to the input), then
cross-attention whose message goes, concatenated with the input, through a feed-forward network (2C -> 8C -> C, GELU,
LayerNorm) before it is added. As the official ``MultiViewFeatureTransformer``, a view's cross-attention queries come
from its self-attention's output, and its keys and values are the other views' maps as they entered the block (the
previous block's output; ``batch_features`` is called once per block). A sine position embedding per window is added
before the first block. Every weight matrix starts xavier-uniform and the LayerNorms of blocks past the sixth start at
zero, as the official (since issue 55: cross-attention read the other views after their self-attention, default init).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


OFFICIAL_LAYERS = 6
"""MVSplat's transformer depth; the official zero-initialises the LayerNorms of any block past it."""


def window_position_embedding(window: tuple[int, int], channels: int, device: torch.device) -> Tensor:
    """``[C, h_w, w_w]`` DETR's normalised sine embedding (``PositionEmbeddingSine``, temperature 10000) of one window:
    C/2 channels for y then C/2 for x, sines and cosines interleaved per frequency."""
    height, width = window
    half = channels // 2
    scale = 2 * math.pi
    y = torch.arange(1, height + 1, dtype=torch.float32, device=device)[:, None].expand(height, width)
    x = torch.arange(1, width + 1, dtype=torch.float32, device=device)[None, :].expand(height, width)
    y, x = y / (height + 1e-6) * scale, x / (width + 1e-6) * scale
    dim = torch.arange(half, dtype=torch.float32, device=device)
    dim = 10000 ** (2 * torch.div(dim, 2, rounding_mode="floor") / half)
    pos_x, pos_y = x[..., None] / dim, y[..., None] / dim
    pos_x = torch.stack([pos_x[..., 0::2].sin(), pos_x[..., 1::2].cos()], dim=-1).flatten(-2)
    pos_y = torch.stack([pos_y[..., 0::2].sin(), pos_y[..., 1::2].cos()], dim=-1).flatten(-2)
    embedding = torch.cat([pos_y, pos_x], dim=-1).permute(2, 0, 1)
    return F.pad(embedding, (0, 0, 0, 0, 0, channels - embedding.shape[0]))


def to_windows(maps: Tensor, splits: int) -> Tensor:
    """``[V, h, w, C]`` -> ``[V, splits^2, (h / splits) (w / splits), C]``."""
    views, height, width, channels = maps.shape
    rows, cols = height // splits, width // splits
    windows = maps.reshape(views, splits, rows, splits, cols, channels).permute(0, 1, 3, 2, 4, 5)
    return windows.reshape(views, splits * splits, rows * cols, channels)


def from_windows(windows: Tensor, splits: int, size: tuple[int, int]) -> Tensor:
    """``to_windows`` undone: ``[V, splits^2, L, C]`` -> ``[V, h, w, C]``."""
    views, _, _, channels = windows.shape
    height, width = size
    rows, cols = height // splits, width // splits
    maps = windows.reshape(views, splits, splits, rows, cols, channels).permute(0, 1, 3, 2, 4, 5)
    return maps.reshape(views, height, width, channels)


def shifted_window_mask(size: tuple[int, int], splits: int, device: torch.device) -> Tensor:
    """``[splits^2, L, L]`` additive mask of shifted windows (Swin's ``SW-MSA`` mask, -100 between tokens that came
    from different regions of the rolled map)."""
    height, width = size
    rows, cols = height // splits, width // splits
    regions = torch.zeros(1, height, width, 1, device=device)
    label = 0
    for row_slice in (slice(0, -rows), slice(-rows, -(rows // 2)), slice(-(rows // 2), None)):
        for col_slice in (slice(0, -cols), slice(-cols, -(cols // 2)), slice(-(cols // 2), None)):
            regions[:, row_slice, col_slice, :] = label
            label += 1
    labels = to_windows(regions, splits)[0, :, :, 0]  # [splits^2, L]
    different = labels[:, None, :] != labels[:, :, None]
    return torch.zeros_like(different, dtype=torch.float32).masked_fill(different, -100.0)


class AttentionLayer(nn.Module):
    """Single-head window attention from ``source`` to ``targets`` (itself for self-attention), with MVSplat's merge,
    LayerNorm and (``feed_forward``) feed-forward network on the concatenated input and message."""

    def __init__(self, channels: int, feed_forward: bool, expansion: int = 4) -> None:
        super().__init__()
        self.query = nn.Linear(channels, channels, bias=False)
        self.key = nn.Linear(channels, channels, bias=False)
        self.value = nn.Linear(channels, channels, bias=False)
        self.merge = nn.Linear(channels, channels, bias=False)
        self.norm = nn.LayerNorm(channels)
        self.feed_forward = None
        if feed_forward:
            self.feed_forward = nn.Sequential(
                nn.Linear(2 * channels, 2 * channels * expansion, bias=False), nn.GELU(),
                nn.Linear(2 * channels * expansion, channels, bias=False))
            self.norm_out = nn.LayerNorm(channels)

    def forward(self, source: Tensor, targets: Tensor, mask: Tensor | None) -> Tensor:
        """``source`` ``[V, n, L, C]`` windows; ``targets`` ``[V, n, M, C]`` the windows each attends to (M = L for
        self-attention, (V - 1) L across views); ``mask`` ``[n, L, M]`` or None."""
        q = self.query(source)
        k, v = self.key(targets), self.value(targets)
        scores = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])
        if mask is not None:
            scores = scores + mask
        message = self.norm(self.merge(torch.softmax(scores, dim=-1) @ v))
        if self.feed_forward is not None:
            message = self.norm_out(self.feed_forward(torch.cat([source, message], dim=-1)))
        return source + message


class MultiViewTransformer(nn.Module):
    """``layers`` blocks of window self-attention and cross-view attention over V maps ``[V, C, h, w]`` (the module
    docstring); h and w must be multiples of ``splits`` (``check_size``)."""

    def __init__(self, channels: int, layers: int, splits: int) -> None:
        super().__init__()
        self.channels, self.splits = channels, splits
        self.blocks = nn.ModuleList(
            nn.ModuleList([AttentionLayer(channels, feed_forward=False), AttentionLayer(channels, feed_forward=True)])
            for _ in range(layers))
        for parameter in self.parameters():
            if parameter.dim() > 1:
                nn.init.xavier_uniform_(parameter)
        for self_attention, cross_attention in list(self.blocks)[OFFICIAL_LAYERS:]:
            for norm in (self_attention.norm, cross_attention.norm_out):  # blocks past the sixth start as identities
                nn.init.zeros_(norm.weight)
                nn.init.zeros_(norm.bias)

    def forward(self, maps: Tensor) -> Tensor:
        views, channels, height, width = maps.shape
        splits = self.splits
        window = (height // splits, width // splits)
        position = window_position_embedding(window, channels, maps.device).to(maps.dtype)
        x = maps + position.repeat(1, splits, splits)[None]
        x = x.permute(0, 2, 3, 1)  # [V, h, w, C]
        shift = (window[0] // 2, window[1] // 2)
        mask = shifted_window_mask((height, width), splits, maps.device).to(maps.dtype) if splits > 1 else None
        for index, (self_attention, cross_attention) in enumerate(self.blocks):
            shifted = splits > 1 and index % 2 == 1
            if shifted:
                x = torch.roll(x, shifts=(-shift[0], -shift[1]), dims=(1, 2))
            windows = to_windows(x, splits)  # [V, n, L, C]
            layer_mask = mask if shifted else None
            entering = windows  # the block's input: the other views' keys and values (the official batch_features)
            windows = self_attention(windows, windows, layer_mask)
            if views > 1:
                others = torch.stack([torch.cat([entering[j] for j in range(views) if j != i], dim=1)
                                      for i in range(views)])  # [V, n, (V - 1) L, C]
                cross_mask = layer_mask.repeat(1, 1, views - 1) if layer_mask is not None else None
                windows = cross_attention(windows, others, cross_mask)
            x = from_windows(windows, splits, (height, width))
            if shifted:
                x = torch.roll(x, shifts=shift, dims=(1, 2))
        return x.permute(0, 3, 1, 2).contiguous()
