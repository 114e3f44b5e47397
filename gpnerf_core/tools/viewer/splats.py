"""The Gaussians of a Gaussian family as viser draws them in the browser: centres, covariances, colours, opacities.

Colours are the Gaussians' own (their harmonics' view-independent part, ``max(0, C0 c_0 + 0.5)``: what a splat looks
like from no particular direction) or their labels' in the palette of the semantic layer and ``render``.
"""

from __future__ import annotations

import numpy as np
import torch

from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.geometry.gaussians.harmonics import SH_C0
from gpnerf_core.geometry.gaussians.projection import rotation_matrices
from gpnerf_core.geometry.gaussians.scene import GaussianScene

SPLAT_COLOURS = ("rgb", "class")
"""What colours the splats: their own colour, or their label's."""


def splat_arrays(scene: GaussianScene, colours: str, num_classes: int) -> dict[str, np.ndarray]:
    """``add_gaussian_splats``'s arrays: ``centers`` ``[G, 3]``, ``covariances`` ``[G, 3, 3]`` (``R S S^T R^T``),
    ``rgbs`` ``[G, 3]`` in [0, 1] (``colours``: ``rgb`` or ``class``; an unlabelled Gaussian keeps its own colour) and
    ``opacities`` ``[G, 1]``, float32."""
    rotation = rotation_matrices(scene.rotations.detach().float().cpu())
    scaled = rotation * scene.scales.detach().float().cpu()[:, None, :]
    covariances = scaled @ scaled.transpose(1, 2)
    rgb = (SH_C0 * scene.harmonics[:, :, 0].detach().float().cpu() + 0.5).clamp(0.0, 1.0)
    if colours == "class" and num_classes > 0:
        labels = scene.labels.detach().cpu()
        labelled = labels >= 0
        palette = vis.colorize_labels(labels.clamp_min(0)[None], num_classes)[0].astype(np.float32) / 255.0
        rgb = torch.where(labelled[:, None], torch.from_numpy(palette).reshape(-1, 3), rgb)
    return {"centers": scene.means.detach().float().cpu().numpy(), "covariances": covariances.numpy(),
            "rgbs": rgb.numpy(), "opacities": scene.opacities.detach().float().cpu()[:, None].numpy()}
