"""gpnerf-core: perception heads on generalizable NeRFs, assembled from pluggy plugins and Hydra configs.

This module is the public import surface: what plugins, examples, notebooks and scripts import, re-exported from the
engine's packages in one place (as ``pytest`` re-exports ``_pytest``). Everything else is the engine's own and may move;
``docs/architecture.md`` lists the packages. A name is imported on first use, so ``import gpnerf_core`` stays cheap.

    from gpnerf_core import ComponentSpec, PerceptionHead, HeadOutput, ConfigError, hookimpl
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from gpnerf_core.runtime.openmp import passive_wait

passive_wait()  # before torch loads OpenMP (runtime/openmp.py says why)

from gpnerf_core.runtime.versions import __version__  # noqa: E402  (imports torch)

_PUBLIC: dict[str, tuple[str, ...]] = {
    # registering plugins
    "gpnerf_core.registry.hookspecs": ("hookimpl",),
    "gpnerf_core.registry.specs": ("ComponentSpec", "DataTool"),
    "gpnerf_core.registry.declarations": (
        "SizeKnob", "fewer", "fractions", "halved_or_none", "one_fewer_or_halved", "part", "size_knob",
    ),
    "gpnerf_core.registry.components": ("get_registry",),
    # the interfaces a component implements
    "gpnerf_core.data.dataset": ("SPLITS", "SceneDataset"),
    "gpnerf_core.data.base": (
        "MAX_FAR", "DatasetBase", "DatasetConfig", "check_depth_range", "check_image_size", "from_launch_dir",
    ),
    "gpnerf_core.interfaces": (
        "DepthSource", "FeatureExtractor", "FeatureProvider", "FieldAggregator", "ImportedWeights", "ImportsWeights",
        "LossSet", "PerceptionHead", "RayAggregator", "StressCase", "ViewSelector",
    ),
    "gpnerf_core.interfaces.stress": ("ChooseSources",),
    "gpnerf_core.interfaces.head": ("Predicts",),
    "gpnerf_core.interfaces.model": (
        "Capabilities", "FamilyHooks", "ModelFamily", "ModelParts", "SemanticMode", "SemanticOutput", "SourceEncoding",
        "TrainingBatch", "one_pass_preview", "parameter_counts",
    ),
    "gpnerf_core.interfaces.training": ("GroupOptions", "TrainingCallback", "TrainingPhase", "TrainingState"),
    "gpnerf_core.geometry.gaussians.rows": ("resize_parameter",),
    "gpnerf_core.config.schema": ("ModelConfig", "RayMarchingConfig"),
    # the records passed between stages
    "gpnerf_core.types": (
        "FeatureMaps", "FieldBlockOutput", "Frame", "HeadOutput", "ImageLossInputs", "ImageOutput", "LossInputs",
        "Prediction", "ProjectedFeatures", "RayBatch",
        "RayBlockOutput", "RayReadout", "RaySamples", "RenderedRays", "SampledMaps", "Scene", "ScenePoints", "SourceViews",
        "StepBatch", "StepOutput", "TargetCamera", "TargetView", "ViewOutput",
    ),
    # one-line errors
    "gpnerf_core.errors": ("ConfigError", "DataError", "GpnerfError", "NonFiniteError", "PluginError"),
    # geometry and checks a dataset or data tool uses
    "gpnerf_core.geometry": (
        "EXPECTED_RIGID", "Projector", "SurfaceSampling", "composite", "compositing_weights", "density_opacity", "importance_depths", "pixel_grid", "points_along_rays", "rays_through_pixels",
        "rigid_transform_problem", "sampling_layout", "stratified_depths", "stratified_inverse_depths", "surface_depths",
    ),
    "gpnerf_core.geometry.projection": ("project_points", "world_to_camera"),
    "gpnerf_core.model.whole_view": ("render_whole_view",),
    "gpnerf_core.model.gaussian_config": ("GaussianRates", "GaussianSceneConfig", "GaussianSetup", "gaussian_setup"),
    "gpnerf_core.model.gaussian_family": ("GaussianFamily", "GaussianHooks"),
    # feature fields (+feature_provider): what a family is handed, the distillation's geometry, the compression
    "gpnerf_core.features.field": ("FeatureField", "FeatureFieldOptions", "at_pixels", "feature_distance",
                                   "lift_to_pixels", "quiet_rng", "to_grid"),
    "gpnerf_core.features.compression": ("FeatureAutoencoder", "ReconstructionError"),
    "gpnerf_core.model.generalized_start": ("GaussianStart", "begin_from_start", "points_start", "predict_start",
                                            "start_overrides"),
    "gpnerf_core.model.context_decoding": (
        "LabelsOrHead", "cells_of_pixels", "decode_checked", "decoded_view_output", "fuse_rendered", "gather_cells",
        "labels_or_head_output", "pixel_cells",
    ),
    "gpnerf_core.geometry.plane_sweep": (
        "PlaneSweep", "ReferenceFrustum", "plane_sweep", "points_in_views", "variance_over_views",
    ),
    "gpnerf_core.geometry.ray_depth": ("DepthBelief", "feature_cost_belief", "source_depth_belief"),
    "gpnerf_core.geometry.gaussians": (
        "Gaussians", "RASTERIZER_BACKENDS", "Rasterized", "rasterize_gaussians", "strided_camera",
    ),
    "gpnerf_core.geometry.gaussians.harmonics": (
        "colour_to_dc", "quaternion_product", "quaternions_of", "sh_coefficients", "sh_colours",
    ),
    "gpnerf_core.geometry.gaussians.scene": ("GaussianScene", "rotate_harmonics"),
    # the public Gaussian strategy: parameters, where they start, density control
    "gpnerf_core.geometry.gaussians.parameters": ("GaussianParameters", "rows_from_gaussians", "rows_from_points"),
    "gpnerf_core.geometry.gaussians.initialisation": (
        "depth_points", "neighbour_scales", "scene_extent", "starting_points",
    ),
    "gpnerf_core.geometry.gaussians.density": (
        "BudgetedStrategy", "DefaultStrategy", "DensityStrategy", "ViewInfo", "append_rows", "keep_rows",
        "reset_opacity", "rotation_matrices", "scaled_step", "split_rows",
    ),
    "gpnerf_core.geometry.pose_sanity": ("check_poses",),
    "gpnerf_core.data.checks": (
        "ValueProblem", "check_scene_files", "check_validation_level", "depth_problem", "far_away_cameras",
    ),
    "gpnerf_core.config.arguments": ("ArgumentParser",),
    "gpnerf_core.runtime.io": ("atomic_write_json",),
    "gpnerf_core.runtime.profiling": ("stage",),
    "gpnerf_core.runtime.device": ("checked_compile_backend",),
    "gpnerf_core.evaluation.instances": ("hungarian", "instance_masks"),
    # queries against features (by example, by embedding, by prototype) and their selections as PLY
    "gpnerf_core.features.queries": (
        "class_prototypes", "example_embedding", "gaussian_feature_matrix", "nearest_prototype",
        "prediction_feature_map", "relevancy", "select_gaussians", "similarity_map", "text_embedding",
        "write_gaussian_selection", "write_point_selection",
    ),
    # a trained model opened from a script as the commands open it (a checkpoint read, its config restored), and the
    # frames and cameras of its dataset
    "gpnerf_core.model.trained": ("load_trained",),
    "gpnerf_core.engine.opening": ("open_trained",),
    "gpnerf_core.data.frames": ("FrameCache",),
    # a feature provider's per-frame features, through the on-disk cache
    "gpnerf_core.features": ("FeatureCache", "build_feature_provider", "frame_features"),
    "gpnerf_core.model.trained_extractor": ("trained_feature_extractor",),
    # composing and building from a script or notebook
    "gpnerf_core.config.compose": ("compose",),
    "gpnerf_core.model.build": ("build_components",),
    # in-process A/B timing of a variant (examples/ab_dropout.py)
    "gpnerf_core.tools.bench.ab": ("alternate", "make_trainer", "timing_lines"),
}
"""Module -> the public names it provides."""

_WHERE = {name: module for module, names in _PUBLIC.items() for name in names}

__all__ = sorted([*_WHERE, "__version__"])


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'gpnerf_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # the same names, for type checkers and readers
    from gpnerf_core.config.arguments import ArgumentParser
    from gpnerf_core.config.compose import compose
    from gpnerf_core.config.schema import ModelConfig, RayMarchingConfig
    from gpnerf_core.data.base import (
        MAX_FAR,
        DatasetBase,
        DatasetConfig,
        check_depth_range,
        check_image_size,
        from_launch_dir,
    )
    from gpnerf_core.data.checks import (
        ValueProblem,
        check_scene_files,
        check_validation_level,
        depth_problem,
        far_away_cameras,
    )
    from gpnerf_core.errors import ConfigError, DataError, GpnerfError, NonFiniteError, PluginError
    from gpnerf_core.evaluation.instances import hungarian, instance_masks
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.engine.opening import open_trained
    from gpnerf_core.features.queries import (
        class_prototypes,
        example_embedding,
        gaussian_feature_matrix,
        nearest_prototype,
        prediction_feature_map,
        relevancy,
        select_gaussians,
        similarity_map,
        text_embedding,
        write_gaussian_selection,
        write_point_selection,
    )
    from gpnerf_core.model.trained import load_trained
    from gpnerf_core.geometry import (
        EXPECTED_RIGID,
        Projector,
        SurfaceSampling,
        composite,
        compositing_weights,
        density_opacity,
        importance_depths,
        pixel_grid,
        points_along_rays,
        rays_through_pixels,
        rigid_transform_problem,
        sampling_layout,
        stratified_depths,
        stratified_inverse_depths,
        surface_depths,
    )
    from gpnerf_core.geometry.plane_sweep import (
        PlaneSweep,
        ReferenceFrustum,
        plane_sweep,
        points_in_views,
        variance_over_views,
    )
    from gpnerf_core.geometry.gaussians import (
        RASTERIZER_BACKENDS, Gaussians, Rasterized, rasterize_gaussians, strided_camera,
    )
    from gpnerf_core.geometry.gaussians.harmonics import (
        colour_to_dc,
        quaternion_product,
        quaternions_of,
        sh_coefficients,
        sh_colours,
    )
    from gpnerf_core.geometry.gaussians.scene import GaussianScene, rotate_harmonics
    from gpnerf_core.geometry.gaussians.parameters import GaussianParameters, rows_from_gaussians, rows_from_points
    from gpnerf_core.geometry.gaussians.initialisation import (
        depth_points,
        neighbour_scales,
        scene_extent,
        starting_points,
    )
    from gpnerf_core.geometry.gaussians.density import (
        BudgetedStrategy,
        DefaultStrategy,
        DensityStrategy,
        ViewInfo,
        append_rows,
        keep_rows,
        reset_opacity,
        rotation_matrices,
        scaled_step,
        split_rows,
    )
    from gpnerf_core.geometry.pose_sanity import check_poses
    from gpnerf_core.geometry.ray_depth import DepthBelief, feature_cost_belief, source_depth_belief
    from gpnerf_core.geometry.projection import project_points, world_to_camera
    from gpnerf_core.model.whole_view import render_whole_view
    from gpnerf_core.model.gaussian_config import GaussianRates, GaussianSceneConfig, GaussianSetup, gaussian_setup
    from gpnerf_core.model.gaussian_family import GaussianFamily, GaussianHooks
    from gpnerf_core.features.field import (
        FeatureField, FeatureFieldOptions, at_pixels, feature_distance, lift_to_pixels, quiet_rng, to_grid,
    )
    from gpnerf_core.features.compression import FeatureAutoencoder, ReconstructionError
    from gpnerf_core.model.generalized_start import (
        GaussianStart,
        begin_from_start,
        points_start,
        predict_start,
        start_overrides,
    )
    from gpnerf_core.model.context_decoding import (
        LabelsOrHead,
        cells_of_pixels,
        decode_checked,
        decoded_view_output,
        fuse_rendered,
        gather_cells,
        labels_or_head_output,
        pixel_cells,
    )
    from gpnerf_core.data.dataset import SPLITS, SceneDataset
    from gpnerf_core.interfaces import (
        DepthSource,
        FeatureExtractor,
        FeatureProvider,
        FieldAggregator,
        ImportedWeights,
        ImportsWeights,
        LossSet,
        PerceptionHead,
        RayAggregator,
        StressCase,
        ViewSelector,
    )
    from gpnerf_core.interfaces.head import Predicts
    from gpnerf_core.interfaces.model import (
        Capabilities,
        FamilyHooks,
        ModelFamily,
        ModelParts,
        SemanticMode,
        SemanticOutput,
        SourceEncoding,
        TrainingBatch,
        one_pass_preview,
        parameter_counts,
    )
    from gpnerf_core.interfaces.training import GroupOptions, TrainingCallback, TrainingPhase, TrainingState
    from gpnerf_core.geometry.gaussians.rows import resize_parameter
    from gpnerf_core.interfaces.stress import ChooseSources
    from gpnerf_core.model.build import build_components
    from gpnerf_core.features import FeatureCache, build_feature_provider, frame_features
    from gpnerf_core.model.trained_extractor import trained_feature_extractor
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.registry.hookspecs import hookimpl
    from gpnerf_core.registry.declarations import (
        SizeKnob,
        fewer,
        fractions,
        halved_or_none,
        one_fewer_or_halved,
        part,
        size_knob,
    )
    from gpnerf_core.registry.specs import ComponentSpec, DataTool
    from gpnerf_core.runtime.device import checked_compile_backend
    from gpnerf_core.runtime.io import atomic_write_json
    from gpnerf_core.runtime.profiling import stage
    from gpnerf_core.tools.bench.ab import alternate, make_trainer, timing_lines
    from gpnerf_core.types import (
        FeatureMaps,
        FieldBlockOutput,
        Frame,
        HeadOutput,
        ImageLossInputs,
        ImageOutput,
        LossInputs,
        Prediction,
        ProjectedFeatures,
        RayBatch,
        RayBlockOutput,
        RayReadout,
        RaySamples,
        RenderedRays,
        SampledMaps,
        Scene,
        ScenePoints,
        SourceViews,
        StepBatch,
        StepOutput,
        TargetCamera,
        TargetView,
        ViewOutput,
    )
