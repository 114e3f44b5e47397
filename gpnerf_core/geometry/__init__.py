"""Camera geometry: rays, samples along rays, projection into source views."""

from gpnerf_core.geometry.compositing import composite, compositing_weights, density_opacity
from gpnerf_core.geometry.poses import EXPECTED_RIGID, rigid_transform_problem
from gpnerf_core.geometry.projection import Projector, project_points, sampling_layout
from gpnerf_core.geometry.rays import pixel_grid, rays_through_pixels
from gpnerf_core.geometry.sampling import (
    SurfaceSampling, importance_depths, points_along_rays, stratified_depths, stratified_inverse_depths, surface_depths,
)

__all__ = [
    "EXPECTED_RIGID",
    "Projector",
    "SurfaceSampling",
    "composite",
    "compositing_weights",
    "density_opacity",
    "importance_depths",
    "pixel_grid",
    "points_along_rays",
    "project_points",
    "rays_through_pixels",
    "rigid_transform_problem",
    "sampling_layout",
    "stratified_depths",
    "stratified_inverse_depths",
    "surface_depths",
]
