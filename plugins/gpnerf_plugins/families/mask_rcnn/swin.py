"""Swin-T (Liu et al., ICCV 2021) as a detection backbone in plain torch, as the official detection code builds it
(``SwinTransformer/Swin-Transformer-Object-Detection``, ``mmdet/models/backbones/swin_transformer.py``): 4x4 patches
embedded to 96 channels, four stages of 2, 2, 6, 2 blocks with 3, 6, 12, 24 heads, window 7, alternate blocks shifted
by 3, relative position biases, patch merging between stages, a LayerNorm on each stage's output. Feature maps that
are not a multiple of the window are padded with zeros at the bottom and right inside each block (24 x 32 tokens at
96 x 128 become 28 x 35) and cropped back after it; the shifted windows' mask is built on the padded grid."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

EMBED_DIM = 96
DEPTHS = (2, 2, 6, 2)
HEADS = (3, 6, 12, 24)
WINDOW = 7
PATCH = 4


def _drop_path(x: Tensor, rate: float, training: bool) -> Tensor:
    """Stochastic depth: each sample's residual branch dropped with probability ``rate`` (kept ones scaled up)."""
    if rate == 0.0 or not training:
        return x
    keep = torch.rand((x.shape[0],) + (1,) * (x.dim() - 1), device=x.device) >= rate
    return x * keep.to(x.dtype) / (1.0 - rate)


def window_partition(x: Tensor, window: int) -> Tensor:
    """``[B, H, W, C]`` (H, W multiples of ``window``) -> ``[B * H/w * W/w, w * w, C]`` windows, row-major."""
    b, h, w, c = x.shape
    x = x.view(b, h // window, window, w // window, window, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, window * window, c)


def window_reverse(windows: Tensor, window: int, h: int, w: int) -> Tensor:
    """The inverse of ``window_partition``: ``[B * h/w * w/w, w * w, C]`` -> ``[B, h, w, C]``."""
    c = windows.shape[-1]
    b = windows.shape[0] // ((h // window) * (w // window))
    x = windows.view(b, h // window, w // window, window, window, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(b, h, w, c)


def shift_mask(h: int, w: int, window: int, shift: int, device: torch.device) -> Tensor:
    """``[nW, w*w, w*w]`` additive attention mask of the shifted windows on an ``h`` x ``w`` (padded) grid: -100
    between tokens that came from different regions before the cyclic shift, 0 within one."""
    regions = torch.zeros(1, h, w, 1, device=device)
    count = 0
    for ys in (slice(0, -window), slice(-window, -shift), slice(-shift, None)):
        for xs in (slice(0, -window), slice(-window, -shift), slice(-shift, None)):
            regions[:, ys, xs, :] = count
            count += 1
    ids = window_partition(regions, window)[..., 0]
    mask = ids[:, None, :] - ids[:, :, None]
    return mask.masked_fill(mask != 0, -100.0).masked_fill(mask == 0, 0.0)


class WindowAttention(nn.Module):
    """Multi-head self-attention within windows, with a learned bias per relative position and head."""

    def __init__(self, dim: int, heads: int, window: int) -> None:
        super().__init__()
        self.heads, self.window = heads, window
        self.scale = (dim // heads) ** -0.5
        self.relative_position_bias_table = nn.Parameter(torch.zeros((2 * window - 1) ** 2, heads))
        nn.init.trunc_normal_(self.relative_position_bias_table, std=0.02)
        coords = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)
        relative = (coords[:, :, None] - coords[:, None, :]).permute(1, 2, 0) + (window - 1)
        self.register_buffer("relative_position_index", relative[..., 0] * (2 * window - 1) + relative[..., 1],
                             persistent=False)
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, mask: Tensor | None) -> Tensor:
        """``[B * nW, N, C]`` tokens of each window (``mask``: ``[nW, N, N]`` or None) -> the same shape."""
        bw, n, c = x.shape
        qkv = self.qkv(x).reshape(bw, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
        attn = q @ k.transpose(-2, -1)
        bias = self.relative_position_bias_table[self.relative_position_index.reshape(-1)]
        attn = attn + bias.reshape(n, n, -1).permute(2, 0, 1)[None]
        if mask is not None:
            windows = mask.shape[0]
            attn = attn.view(bw // windows, windows, self.heads, n, n) + mask[None, :, None]
            attn = attn.view(bw, self.heads, n, n)
        x = (attn.softmax(dim=-1) @ v).transpose(1, 2).reshape(bw, n, c)
        return self.proj(x)


class SwinBlock(nn.Module):
    """LayerNorm, (shifted) window attention and a residual; LayerNorm, a 4x MLP with GELU and a residual."""

    def __init__(self, dim: int, heads: int, window: int, shift: int, drop_path: float) -> None:
        super().__init__()
        self.window, self.shift, self.drop_path = window, shift, drop_path
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, heads, window)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: Tensor, h: int, w: int) -> Tensor:
        """``[B, h * w, C]`` -> the same shape."""
        b, _, c = x.shape
        win = self.window
        y = self.norm1(x).view(b, h, w, c)
        pad_b, pad_r = (win - h % win) % win, (win - w % win) % win
        y = F.pad(y, (0, 0, 0, pad_r, 0, pad_b))
        hp, wp = h + pad_b, w + pad_r
        mask = None
        if self.shift:
            y = torch.roll(y, shifts=(-self.shift, -self.shift), dims=(1, 2))
            mask = shift_mask(hp, wp, win, self.shift, x.device)
        y = window_reverse(self.attn(window_partition(y, win), mask), win, hp, wp)
        if self.shift:
            y = torch.roll(y, shifts=(self.shift, self.shift), dims=(1, 2))
        y = y[:, :h, :w].reshape(b, h * w, c)
        x = x + _drop_path(y, self.drop_path, self.training)
        return x + _drop_path(self.mlp(self.norm2(x)), self.drop_path, self.training)


class PatchMerging(nn.Module):
    """Each 2x2 group of tokens concatenated (padded to even sizes first), normalised, and projected 4C -> 2C."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(4 * dim)
        self.reduction = nn.Linear(4 * dim, 2 * dim, bias=False)

    def forward(self, x: Tensor, h: int, w: int) -> tuple[Tensor, int, int]:
        b, _, c = x.shape
        x = F.pad(x.view(b, h, w, c), (0, 0, 0, w % 2, 0, h % 2))
        x = torch.cat([x[:, 0::2, 0::2], x[:, 1::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 1::2]], dim=-1)
        h, w = x.shape[1], x.shape[2]
        return self.reduction(self.norm(x.reshape(b, h * w, 4 * c))), h, w


class SwinTransformer(nn.Module):
    """Swin-T's four stages; ``forward`` gives each stage's normalised output as a map (strides 4, 8, 16, 32;
    ``channels`` 96, 192, 384, 768).

    Args:
        drop_path: the stochastic-depth rate of the last block, rising linearly from 0 (Swin-T Mask R-CNN: 0.2).
    """

    def __init__(self, drop_path: float = 0.2) -> None:
        super().__init__()
        self.patch_embed = nn.Conv2d(3, EMBED_DIM, PATCH, stride=PATCH)
        self.patch_norm = nn.LayerNorm(EMBED_DIM)
        rates = torch.linspace(0, drop_path, sum(DEPTHS)).tolist()
        self.stages, self.merges, self.norms = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.channels, first = [], 0
        for i, (depth, heads) in enumerate(zip(DEPTHS, HEADS)):
            dim = EMBED_DIM * 2 ** i
            self.stages.append(nn.ModuleList(
                SwinBlock(dim, heads, WINDOW, 0 if j % 2 == 0 else WINDOW // 2, rates[first + j]) for j in range(depth)))
            first += depth
            self.norms.append(nn.LayerNorm(dim))
            self.merges.append(PatchMerging(dim) if i < len(DEPTHS) - 1 else nn.Identity())
            self.channels.append(dim)
        self.apply(self._init)

    @staticmethod
    def _init(module: nn.Module) -> None:
        if isinstance(module, nn.Linear):
            nn.init.trunc_normal_(module.weight, std=0.02)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.LayerNorm):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)

    def forward(self, images: Tensor) -> list[Tensor]:
        """``[N, 3, H, W]`` -> four maps ``[N, 96 * 2^k, ceil(H / (4 * 2^k)), ceil(W / (4 * 2^k))]``."""
        pad_b, pad_r = (-images.shape[2]) % PATCH, (-images.shape[3]) % PATCH
        x = self.patch_embed(F.pad(images, (0, pad_r, 0, pad_b)))
        b, c, h, w = x.shape
        x = self.patch_norm(x.flatten(2).transpose(1, 2))
        outs = []
        for blocks, norm, merge in zip(self.stages, self.norms, self.merges):
            for block in blocks:
                x = block(x, h, w)
            outs.append(norm(x).view(b, h, w, -1).permute(0, 3, 1, 2).contiguous())
            if isinstance(merge, PatchMerging):
                x, h, w = merge(x, h, w)
        return outs
