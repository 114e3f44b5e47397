"""Loss terms as pure functions of tensors (no weights, no gradient stops: the loss set applies those)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import ConfigError


def rgb_mse(pred: Tensor, target: Tensor) -> Tensor:
    """Mean squared colour error over rays and channels.

    GNT's per-channel MSE. GP-NeRF's code instead sums the square over the 3 channels (3x this value) and
    scales it by 0.25, i.e. 0.75x this value per pass.

    Args:
        pred, target: ``[R, 3]``.
    """
    return (pred - target).square().mean()


def rgb_l1(pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute colour error over rays and channels (3D Gaussian splatting's ``l1_loss``). ``[R, 3]`` each."""
    return (pred.float() - target.float()).abs().mean()


def cross_entropy(logits: Tensor, labels: Tensor, ignore_index: int) -> Tensor:
    """Cross-entropy averaged over the pixels whose label is not ``ignore_index``; 0 when there is none.

    Args:
        logits: ``[N, K, H, W]``.
        labels: ``[N, H, W]`` int64 in ``[0, K)`` or ``ignore_index``.
    """
    if logits.dim() != 4 or labels.shape != (logits.shape[0], *logits.shape[2:]):
        raise ConfigError(
            f"cross-entropy got logits {tuple(logits.shape)} and labels {tuple(labels.shape)}; "
            f"expected [N, K, H, W] and [N, H, W] of the same size"
        )
    valid = labels != ignore_index
    count = int(valid.sum())
    if count:
        lowest, highest = int(labels[valid].min()), int(labels[valid].max())
        if lowest < 0 or highest >= logits.shape[1]:
            bad = lowest if lowest < 0 else highest
            raise ConfigError(
                f"label {bad} is outside the head's {logits.shape[1]} classes [0, {logits.shape[1]}) and is not "
                f"ignore_index={ignore_index}; check the head's num_outputs against the dataset"
            )
    # A sum over valid pixels divided by their count stays finite (and zero) when every pixel is ignored.
    total = F.cross_entropy(logits, labels, ignore_index=ignore_index, reduction="sum")
    return total / max(count, 1)


def cosine_distance(student: Tensor, teacher: Tensor) -> Tensor:
    """Mean over rays of ``1 - cos(student, teacher)``.

    Args:
        student, teacher: ``[R, C]``.
    """
    if student.shape != teacher.shape:
        raise ConfigError(
            f"semantic distillation got rendered features {tuple(student.shape)} and teacher "
            f"{tuple(teacher.shape)}; expected the same [R, C]"
        )
    return (1.0 - F.cosine_similarity(student, teacher, dim=-1)).mean()


def centre_from_weights(weights: Tensor) -> Tensor:
    """Index of the largest weight of each ray: ``[R, S]`` -> ``[R]`` int64."""
    return weights.argmax(dim=-1)


def centre_from_depth(depths: Tensor, target_depth: Tensor, weights: Tensor) -> Tensor:
    """Index of the sample nearest the ground-truth depth; rays with unknown depth (<= 0) use the weights.

    Args:
        depths: ``[R, S]`` sample depths in metres.
        target_depth: ``[R]`` metres, 0 = unknown.
        weights: ``[R, S]`` predicted weights, for the fallback.
    Returns:
        ``[R]`` int64 sample indices.
    """
    if target_depth.shape != depths.shape[:1]:
        raise ConfigError(
            f"gt_depth window centre got target depths {tuple(target_depth.shape)} for samples "
            f"{tuple(depths.shape)}; expected [R]"
        )
    nearest = (depths - target_depth[:, None]).abs().argmin(dim=-1)
    known = torch.isfinite(target_depth) & (target_depth > 0)
    return torch.where(known, nearest, centre_from_weights(weights))


def sample_window(centre: Tensor, num_samples: int, half_width: int) -> Tensor:
    """Sample indices ``centre - half_width .. centre + half_width``, shifted (never wrapped) into ``[0, S-1]``.

    Every ray gets ``min(2 * half_width + 1, S)`` distinct indices.

    Args:
        centre: ``[R]`` int64 indices in ``[0, S)``.
        num_samples: S.
        half_width: N_p, in sample indices.
    Returns:
        ``[R, W]`` int64, ascending along each row.
    """
    width = min(2 * half_width + 1, num_samples)
    start = (centre - half_width).clamp(min=0, max=num_samples - width)
    return start[:, None] + torch.arange(width, device=centre.device)


def depth_guided_distance(sample_features: Tensor, teacher: Tensor, window: Tensor, push_away: bool) -> Tensor:
    """Depth-guided distillation: mean of ``1 - cos`` over the window samples of every ray.

    With ``push_away`` the samples outside the window add the mean of ``max(0, cos)`` over them.

    Args:
        sample_features: ``[R, S, C]`` per-sample semantic features.
        teacher: ``[R, C]`` teacher feature of each ray.
        window: ``[R, W]`` sample indices from ``sample_window``.
        push_away: also push the samples outside the window away from the teacher.
    """
    num_rays, num_samples, channels = sample_features.shape
    if teacher.shape != (num_rays, channels):
        raise ConfigError(
            f"depth-guided distillation got sample features {tuple(sample_features.shape)} and teacher "
            f"{tuple(teacher.shape)}; expected [R, S, C] and [R, C]"
        )
    if not push_away:
        inside = sample_features.gather(1, window[..., None].expand(-1, -1, channels))
        return (1.0 - F.cosine_similarity(inside, teacher[:, None, :], dim=-1)).mean()
    cos = F.cosine_similarity(sample_features, teacher[:, None, :], dim=-1)
    in_window = torch.zeros_like(cos, dtype=torch.bool).scatter_(1, window, True)
    pull = (1.0 - cos[in_window]).mean()
    outside = cos[~in_window]
    if outside.numel() == 0:
        return pull
    return pull + outside.clamp(min=0.0).mean()


SSIM_WINDOW = 11
"""Pixels: the side of the SSIM window (3DGS's ``ssim(window_size=11)``)."""

SSIM_SIGMA = 1.5
"""Pixels: the standard deviation of the SSIM window's Gaussian."""


def ssim_map(pred: Tensor, target: Tensor) -> Tensor:
    """``[C, H, W]`` per-pixel SSIM of two images on values in [0, 1], as 3D Gaussian splatting's official
    ``utils/loss_utils.py``: an 11-pixel Gaussian window of sigma 1.5 applied per channel by ``F.conv2d`` with
    ``padding=window_size // 2`` (zeros beyond the border: the border pixels' means and variances include zeros),
    ``C1 = 0.01^2``, ``C2 = 0.03^2``. (The evaluation metric ``ssim/gaussian11`` is another function and unchanged.)

    Args:
        pred, target: ``[C, H, W]``, same shape.
    """
    channels = pred.shape[0]
    offsets = torch.arange(SSIM_WINDOW, dtype=pred.dtype, device=pred.device) - SSIM_WINDOW // 2
    line = torch.exp(-offsets.square() / (2 * SSIM_SIGMA ** 2))
    line = line / line.sum()
    window = (line[:, None] * line[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()

    def blur(image: Tensor) -> Tensor:
        return F.conv2d(image[None], window, padding=SSIM_WINDOW // 2, groups=channels)[0]

    target = target.to(pred.dtype)
    mu_p, mu_t = blur(pred), blur(target)
    var_p = blur(pred * pred) - mu_p.square()
    var_t = blur(target * target) - mu_t.square()
    covariance = blur(pred * target) - mu_p * mu_t
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_p * mu_t + c1) * (2 * covariance + c2)) / ((mu_p.square() + mu_t.square() + c1) * (var_p + var_t + c2))


def structural_dissimilarity(pred: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
    """``1 - SSIM`` of two images, averaged over pixels and channels: the D-SSIM of 3D Gaussian splatting, its
    zero-padded SSIM (``ssim_map``; a reflect-padded ``kornia.metrics.ssim`` before issue 55).

    Args:
        pred, target: ``[C, H, W]``.
        valid: ``[H, W]`` bool, the pixels averaged over (None: all).
    """
    if pred.shape != target.shape or pred.dim() != 3:
        raise ConfigError(f"SSIM got images {tuple(pred.shape)} and {tuple(target.shape)}; expected the same [C, H, W]")
    similarity = ssim_map(pred, target)  # [C, H, W]
    if valid is None:
        return 1.0 - similarity.mean()
    weights = valid.to(similarity.dtype)[None].expand_as(similarity)
    return 1.0 - (similarity * weights).sum() / weights.sum().clamp_min(1.0)
