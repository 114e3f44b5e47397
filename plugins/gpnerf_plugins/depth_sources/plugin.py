"""Registers the built-in depth sources."""

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_plugins.depth_sources.sweeps import CostVolumeConfig, CostVolumeDepth, RecordedDepth, SourceDepthConfig


@hookimpl
def gpnerf_register_depth_sources() -> list[ComponentSpec]:
    return [
        ComponentSpec("cost_volume", CostVolumeDepth, CostVolumeConfig,
                      "plane sweep of the source views' radiance features along each ray (MVSNet's variance cost)"),
        ComponentSpec("source_depth", RecordedDepth, SourceDepthConfig,
                      "the source views' recorded depth, swept along each ray (datasets with depth maps)"),
    ]
