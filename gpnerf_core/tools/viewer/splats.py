"""The Gaussians of a Gaussian family as viser draws them in the browser: centres, covariances, colours, opacities.

Colours are the Gaussians' own (their harmonics' view-independent part, ``max(0, C0 c_0 + 0.5)``: what a splat looks
like from no particular direction), their labels' in the palette of the semantic layer and ``render``, or a query's
relevancy (turbo from the threshold to 1 on the Gaussians that reach it, the others their own colour at a quarter).
"""

from __future__ import annotations

import numpy as np
import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.features.queries import gaussian_feature_matrix, relevancy
from gpnerf_core.geometry.gaussians.harmonics import SH_C0
from gpnerf_core.geometry.gaussians.projection import rotation_matrices
from gpnerf_core.geometry.gaussians.scene import GaussianScene

SPLAT_COLOURS = ("rgb", "class", "relevancy")
"""What colours the splats: their own colour, their label's, or a query's relevancy."""


def splat_arrays(scene: GaussianScene, colours: str, num_classes: int, query: torch.Tensor | None = None,
                 threshold: float = 0.5) -> dict[str, np.ndarray]:
    """``add_gaussian_splats``'s arrays: ``centers`` ``[G, 3]``, ``covariances`` ``[G, 3, 3]`` (``R S S^T R^T``),
    ``rgbs`` ``[G, 3]`` in [0, 1] (``colours``: ``rgb``, ``class``, an unlabelled Gaussian keeping its own colour, or
    ``relevancy`` to ``query`` ``[C]`` at ``threshold``) and ``opacities`` ``[G, 1]``, float32.

    Raises:
        ConfigError: ``relevancy`` for Gaussians without features, or a query of another dimension (naming both).
    """
    rotation = rotation_matrices(scene.rotations.detach().float().cpu())
    scaled = rotation * scene.scales.detach().float().cpu()[:, None, :]
    covariances = scaled @ scaled.transpose(1, 2)
    rgb = (SH_C0 * scene.harmonics[:, :, 0].detach().float().cpu() + 0.5).clamp(0.0, 1.0)
    if colours == "class" and num_classes > 0:
        labels = scene.labels.detach().cpu()
        labelled = labels >= 0
        palette = vis.colorize_labels(labels.clamp_min(0)[None], num_classes)[0].astype(np.float32) / 255.0
        rgb = torch.where(labelled[:, None], torch.from_numpy(palette).reshape(-1, 3), rgb)
    if colours == "relevancy" and query is not None:
        rgb = relevancy_colours(scene, rgb, query, threshold)
    return {"centers": scene.means.detach().float().cpu().numpy(), "covariances": covariances.numpy(),
            "rgbs": rgb.numpy(), "opacities": scene.opacities.detach().float().cpu()[:, None].numpy()}


def relevancy_colours(scene: GaussianScene, rgb: torch.Tensor, query: torch.Tensor, threshold: float) -> torch.Tensor:
    """``[G, 3]`` colours: turbo from ``threshold`` (blue) to 1 (red) where a Gaussian's relevancy to ``query`` reaches
    the threshold, ``rgb`` at a quarter elsewhere."""
    matrix = gaussian_feature_matrix(scene)
    if matrix is None:
        raise ConfigError("these Gaussians carry no features (no feature field, no semantic features) to colour by "
                          "relevancy")
    scores = relevancy(matrix.detach().float().cpu(), query.float().cpu())
    span = max(1.0 - float(threshold), 1e-6)
    turbo = vis._apply_colormap(((scores - float(threshold)) / span).numpy(), "turbo").astype(np.float32) / 255.0
    return torch.where((scores >= float(threshold))[:, None], torch.from_numpy(turbo), rgb / 4)
