"""A parameter replaced by one with more or fewer rows while training, its optimizer state following the rows.

3D Gaussian splatting adds Gaussians (clone, split) and removes them (prune) every few hundred steps; each Gaussian is
a row of every per-Gaussian parameter. The official code swaps each parameter in the optimizer and cuts or extends its
Adam moments to match (``GaussianModel.cat_tensors_to_optimizer``, ``_prune_optimizer``,
``replace_tensor_to_optimizer``); ``resize_parameter`` is that one operation for any parameter of any family
(``Capabilities.changes_size``), and the public Gaussian parameters and density strategies are built on it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

ROW_STATE = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")
"""Adam's per-element state; its ``step`` counts optimizer steps and is kept as it is."""


def resize_parameter(optimizer: torch.optim.Optimizer, parameter: nn.Parameter, values: Tensor,
                     kept: Tensor | None = None) -> nn.Parameter:
    """A new parameter holding ``values`` that takes ``parameter``'s place in ``optimizer`` (same group and rate).

    Its optimizer state follows the rows: the first ``k`` rows of ``values`` continue the old rows ``kept`` (a bool mask
    or int64 indices over the old rows, ``k`` of them; None: every old row, in order) and keep their moments; the
    other rows are new and start with zero moments. Pruning is ``values = old[mask], kept = mask``; adding rows is
    ``values = cat([old, new]), kept = None``; new values for every row with fresh moments (3DGS's opacity reset) is
    ``kept = torch.zeros(0, dtype=torch.long)``.

    Args:
        parameter: ``[N, ...]`` a parameter of the model, in ``optimizer`` or not (then only the new one is made).
        values: ``[M, ...]`` the new rows, the same trailing shape.

    Returns:
        The new ``nn.Parameter`` (requires grad, no gradient yet): the caller sets it on its module.
    """
    if tuple(values.shape[1:]) != tuple(parameter.shape[1:]):
        raise ValueError(f"resize_parameter: values {list(values.shape)} do not continue a parameter of shape "
                         f"{list(parameter.shape)} (only the first dimension may change)")
    if kept is None:
        kept = torch.arange(parameter.shape[0], device=parameter.device)
    elif kept.dtype == torch.bool:
        kept = kept.nonzero().flatten()
    if kept.numel() > values.shape[0]:
        raise ValueError(f"resize_parameter: {kept.numel()} kept rows but only {values.shape[0]} new rows")
    replacement = nn.Parameter(values.detach().clone().contiguous(), requires_grad=parameter.requires_grad)
    for group in optimizer.param_groups:
        for index, member in enumerate(group["params"]):
            if member is not parameter:
                continue
            group["params"][index] = replacement
            state = optimizer.state.pop(parameter, None)
            if state:
                added = values.shape[0] - kept.numel()
                for key in ROW_STATE:
                    if key in state:
                        old = state[key][kept]
                        state[key] = torch.cat([old, old.new_zeros((added, *old.shape[1:]))]) if added else old
                optimizer.state[replacement] = state
            return replacement
    return replacement
