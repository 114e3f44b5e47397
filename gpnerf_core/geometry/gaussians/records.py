"""What the rasterizer takes and returns: ``Gaussians`` (activated, world frame) and ``Rasterized`` (one view).

Conventions are ``gpnerf_core.types``'s: OpenCV cameras, camera-to-world poses, metres, depth = camera z, pixel centres
at integer coordinates (pixel column i has its centre at u = i).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class Gaussians:
    """G 3D Gaussians, activated (a model stores logs of scales and logits of opacities and activates them first).

    Attributes:
        means: ``[G, 3]`` centres in the world frame, metres.
        scales: ``[G, 3]`` standard deviations along the Gaussian's own axes, metres (>= 0; 0 is a flat or degenerate
            axis, allowed).
        rotations: ``[G, 4]`` quaternions ``(w, x, y, z)`` turning the local axes into the world frame; any norm (the
            rasterizer normalises them).
        opacities: ``[G]`` in [0, 1].
        features: ``[G, C]`` whatever is composited: colours already evaluated (no spherical harmonics inside),
            semantic features, class scores.
    """

    means: Tensor
    scales: Tensor
    rotations: Tensor
    opacities: Tensor
    features: Tensor

    def __post_init__(self) -> None:
        count = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {"means": (count, 3), "scales": (count, 3), "rotations": (count, 4), "opacities": (count,)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape or count < 0:
                raise ValueError(f"Gaussians.{name} {list(getattr(self, name).shape)}: expected {list(shape)} "
                                 f"(means [G, 3], scales [G, 3], rotations [G, 4], opacities [G], features [G, C])")
        if self.features.ndim != 2 or self.features.shape[0] != count:
            raise ValueError(f"Gaussians.features {list(self.features.shape)}: expected [{count}, C]")

    @property
    def count(self) -> int:
        """G."""
        return int(self.means.shape[0])

    @property
    def channels(self) -> int:
        """C."""
        return int(self.features.shape[1])


@dataclass(frozen=True)
class Rasterized:
    """One view rendered from Gaussians.

    Attributes:
        features: ``[H, W, C]`` ``sum_i w_i f_i``, plus ``background * (1 - alpha)`` when a background was given.
        depth: ``[H, W]`` ``sum_i w_i z_i`` (camera z of the centres, metres), NOT normalised by ``alpha`` (divide for
            the expected depth).
        alpha: ``[H, W]`` accumulated opacity ``1 - T_final``.
        means2d: ``[G, 2]`` projected centres ``(u, v)`` in pixels, in the autograd graph: ``means2d.retain_grad()``
            before ``backward()`` gives the view-space positional gradient 3DGS densifies by. Meaningless for culled
            Gaussians.
        radii: ``[G]`` int32 footprint radius ``ceil(3 sqrt(lambda_max))`` of the 2D covariance, pixels (the official
            rasterizer's: 3DGS prunes by it); 0 for a Gaussian that reaches no pixel (culled: behind, outside the
            image, or opacity below 1/255).
        culled_behind: Gaussians with camera z <= ``near``.
        clamped: Gaussians in front whose 2D covariance was singular to working precision before the low-pass filter
            (a zero scale seen edge-on, all scales 0): its determinant is clamped at 0 and the +0.3 filter makes it
            invertible; counted, never an error.
        backend: the backend that composited (``"auto"`` resolved).
    """

    features: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    culled_behind: int
    clamped: int
    backend: str
