"""``python -m gpnerf_core export checkpoint=<.pt> [export.scene=...] [export.frames=eval|train|all] [export.voxel=0.02]``.

What the model sees, as a point cloud: the chosen frames of one scene are rendered at their own cameras (each from the
training frames but itself, as evaluation does), every rendered cell becomes a point at its rendered depth with its
rendered colour and predicted class (or instance slot), and the views are fused as multi-view stereo fuses depth maps:
a point stays where at least ``export.min_views`` other exported views rendered a surface at the same depth (within
``export.tolerance``), which drops the floaters and the empty-space depths a single view cannot tell apart; an
optional voxel grid merges the rest (``export.voxel``). Writes into the run folder, all or none (staged):

- ``points.ply``: binary PLY, ``x y z`` (float, metres, the dataset's world frame), ``red green blue`` (uchar, the
  rendered colour) and ``label`` (int: the class id or instance slot, -1 for a model without scores), readable by
  Open3D, MeshLab, CloudCompare, trimesh and viser's loaders (an unknown property is passed over);
- ``points_labels.ply``: the same points coloured by label in the palette of ``render`` and the viewer (with scores);
- ``gaussians.ply``, for a family that renders 3D Gaussians (``ModelFamily.scene_gaussians``; a feed-forward one's
  from the source views of the first exported frame): the standard 3D Gaussian splatting PLY (``x y z``, ``f_dc_*``,
  ``f_rest_*``, ``opacity``, ``scale_*``, ``rot_*``) with each Gaussian's ``label``, which splat viewers open. It is
  written whatever the fusion keeps: where no point is kept, it and ``export.json`` (with a ``note`` saying why) are
  all that is written, and the reason is said on stderr;
- ``legend.png`` (classes) and ``export.json``: the frames, the settings, the point counts, the class names;
- with a query by example (``export.query.pixel=[x,y]`` or ``export.query.box=[x0,y0,x1,y1]`` in frame
  ``export.query.frame``): ``selection_gaussians.ply`` (the Gaussians whose features are at least
  ``export.query.threshold`` similar to the example, a Gaussian family) and ``selection_points.ply`` (the kept points
  whose rendered features are), each with its ``relevancy`` (docs/features.md, "Queries").
"""

from __future__ import annotations

import sys
import time
from functools import partial
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import claim_run_folder
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.features.queries import prediction_feature_map, prediction_feature_source
from gpnerf_core.geometry.point_fusion import cell_scores, inside_bounds
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.runtime.staging import Write, write_staged

FRAME_CHOICES = ("eval", "train", "all")
STAGING_PREFIX = ".export.partial-"
"""The folder inside the run folder that an export writes into before renaming its outputs into place."""


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(export_task, argv, "export")


def exported_frames(scene: Any, which: str, every: int) -> list[int]:
    """The frame indices ``export.frames`` / ``export.every`` choose in ``scene``, in order."""
    if which not in FRAME_CHOICES:
        raise ConfigError(f"export.frames={which!r}; expected one of: {', '.join(FRAME_CHOICES)}")
    chosen = {"eval": scene.eval_frames, "train": scene.train_frames,
              "all": range(scene.num_frames)}[which]
    indices = list(chosen)[::every]
    if not indices:
        raise ConfigError(f"export.frames={which}: scene {scene.name!r} has no {which} frames; "
                          f"choose {' or '.join(c for c in FRAME_CHOICES if c != which)}")
    return indices


def checked_min_views(min_views: int, frames: int) -> int:
    """``export.min_views``, refused where more views must agree than there are other exported views."""
    if min_views > frames - 1:
        raise ConfigError(f"export.min_views={min_views}: only {frames} frame(s) are exported, so a point can "
                          f"agree with at most {frames - 1} other view(s); lower it (0 keeps every point) or "
                          "export more frames (export.frames, export.every)")
    return min_views


@job
def export_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from tqdm import tqdm

    from gpnerf_core.data.dataset import chosen_scene
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.geometry.point_fusion import agreeing_views, concatenate, voxel_merge
    from gpnerf_core.model.view_inputs import view_inputs

    settings = cfg.export
    loaded = open_trained(handover.trained, cfg=cfg, command="export", validated=handover.validated,
                          device=dist.device)
    components = loaded.components
    model = components.model.eval()
    frames = FrameCache(components.dataset, dist.device)
    name = chosen_scene(components.dataset, "export.scene", str(settings.scene), loaded.fitted)
    scene = frames.scene(name)
    indices = exported_frames(scene, str(settings.frames), int(settings.every))
    min_views = checked_min_views(int(settings.min_views), len(indices))
    stride = int(settings.stride) or int(cfg.eval.render_stride)
    if stride and (scene.height % stride or scene.width % stride):
        key = "export.stride" if int(settings.stride) else "eval.render_stride (export.stride=0 takes it)"
        raise ConfigError(f"{key}={stride}: scene {name!r} is {scene.height}x{scene.width}; expected a stride that "
                          "divides both sides")
    owners = model.hooks.output_owners(component_names(cfg))
    asked = query_asked(settings.query, scene)
    folder, _ = claim_run_folder(cfg, dist, resuming=False)
    with folder:
        for note in loaded.notes:
            print(f"note: {note}", file=sys.stderr)
        started = time.perf_counter()
        views, clouds, sensor_depths, first, feature_maps, feature_source = [], [], [], None, {}, None

        def render_frame(index: int) -> Any:
            camera = frames.camera(scene, frames.frame(scene, index))
            given = view_inputs(model, frames, components.view_selector, scene, camera.c2w,
                                int(cfg.model.num_source_views), exclude=index)
            with torch.no_grad():
                prediction = model.predict(camera, given.sources, stride=stride, chunk_rays=int(cfg.eval.chunk_rays),
                                           features=given.features)
            prediction.check_finite(owners, f"export: scene {name!r} frame {index}")
            return given, camera, prediction

        for index in tqdm(indices, desc="export", unit="frame", file=sys.stderr, dynamic_ncols=True):
            frame = frames.frame(scene, index)
            given, camera, prediction = render_frame(index)
            first = first or given
            if asked:
                feature_maps[index] = prediction_feature_map(prediction)
                feature_source = feature_source or prediction_feature_source(prediction)
            view, cloud = rendered_points(prediction, camera, model.semantic_output)
            views.append(view)
            clouds.append(cloud)
            sensor_depths.append(cell_depth(frame.depth.float().cpu(), prediction.stride, view.depth.shape))
        agreeing = agreeing_views(views, float(settings.tolerance))
        keeps = [(count >= min_views) & inside_bounds(view.depth.reshape(-1), scene)
                 for count, view in zip(agreeing, views)]
        kept = [cloud_subset(cloud, keep) for cloud, keep in zip(clouds, keeps)]
        errors = depth_errors(views, sensor_depths, keeps)
        rendered = sum(len(cloud) for cloud in clouds)
        fused = concatenate(kept)
        merged = voxel_merge(fused, float(settings.voxel))
        splats = scene_gaussians(model, first, scene, owners, name)
        selection = None
        if asked:
            example = asked.get("frame", indices[0])
            if example not in feature_maps:
                feature_maps[example] = prediction_feature_map(render_frame(example)[2])
            selection = query_selection(settings.query, scene, feature_maps, example, indices, clouds, keeps,
                                        [tuple(view.depth.shape) for view in views], splats, float(settings.voxel),
                                        feature_source)
        empty = None
        if len(merged) == 0:  # a Gaussian family's Gaussians are written whatever the fusion keeps
            empty = (f"no point of scene {name!r} is inside its depth bounds and seen by {min_views} other view(s) "
                     f"within {settings.tolerance:g}; lower export.min_views or raise export.tolerance")
            if splats is None:
                raise DataError(f"export: {empty}")
        seconds = time.perf_counter() - started
        result = _result(cfg, loaded, components, name, indices, prediction.stride, rendered, len(fused), len(merged),
                         seconds)
        result["depth_error_m"] = errors
        if splats is not None:
            result["gaussians"] = {"count": splats.count, "source_frames": list(first.indices),
                                   "file": "gaussians.ply"}
            result["outputs"].insert(-1, "gaussians.ply")
        if empty is not None:
            result["note"] = f"the point cloud is not written: {empty}"
            result["outputs"] = ["gaussians.ply", "export.json"]
        writes = _writes(merged, result, components, splats)
        if selection is not None:
            result["query"] = selection.pop("record")
            files = selection_writes(selection, result)
            result["outputs"][-1:-1] = [file for file, _ in files]
            writes[-1:-1] = files
        write_staged(folder.path, writes, STAGING_PREFIX)
        if empty is not None:
            print(f"export: {empty}: wrote the model's {splats.count} Gaussians only, to "
                  f"{folder.path / 'gaussians.ply'}", file=sys.stderr)
        else:
            print(f"exported {len(merged)} points of {name} from {len(indices)} frames ({rendered} rendered, "
                  f"{len(fused)} agreed by {min_views}+ views) to {folder.path / 'points.ply'}")
        if selection is not None:
            query = result["query"]
            found = [f"{query['gaussians_selected']} Gaussians"] if "gaussians_selected" in query else []
            print(f"query ({query['features']}, relevancy >= {query['threshold']:g}): "
                  f"{', '.join([*found, str(query['points_selected']) + ' points'])} selected"
                  + (f" -> {', '.join(str(folder.path / f) for f, _ in files)}" if files else f"; {query.get('note')}"))
    return result


def query_asked(query: Any, scene: Any) -> dict[str, Any]:
    """The example ``export.query`` gives (``{"pixel"|"box": [...], "frame": index}``, no frame: the first exported),
    or an empty dict (no query).

    Raises:
        ConfigError: both or a malformed ``pixel`` / ``box``, a frame the scene does not have.
    """
    pixel, box = list(query.pixel or []), list(query.box or [])
    if not pixel and not box:
        return {}
    if pixel and box:
        raise ConfigError(f"export.query.pixel={pixel} and export.query.box={box}: expected one of them")
    if pixel and len(pixel) != 2:
        raise ConfigError(f"export.query.pixel={pixel}: expected [x, y] (full-image pixel coordinates)")
    if box and len(box) != 4:
        raise ConfigError(f"export.query.box={box}: expected [x0, y0, x1, y1] (full-image pixel coordinates)")
    asked: dict[str, Any] = {"pixel": [float(v) for v in pixel]} if pixel else {"box": [float(v) for v in box]}
    frame = int(query.frame)
    if frame != -1:
        if not 0 <= frame < scene.num_frames:
            raise ConfigError(f"export.query.frame={frame}: scene {scene.name!r} has frames 0-{scene.num_frames - 1} "
                              "(-1 = the first exported frame)")
        asked["frame"] = frame
    return asked


def query_selection(query: Any, scene: Any, feature_maps: dict[int, Any], example: int, indices: list[int],
                    clouds: list[Any], keeps: list[torch.Tensor], grids: list[tuple[int, int]], splats: Any,
                    voxel: float, source: str | None = None) -> dict[str, Any]:
    """The Gaussians and kept points at least ``export.query.threshold`` similar to the example (its feature map's
    cells, ``features.queries``): ``{"gaussians": (scene, selected, scores) | None, "points": cloud | None,
    "record": export.json's ``query``}``.

    Raises:
        ConfigError: a model without a feature map; a Gaussian feature matrix of another dimension (both named).
    """
    from gpnerf_core.features.queries import (
        example_embedding, gaussian_feature_matrix, relevancy, select_gaussians, similarity_map,
    )
    from gpnerf_core.geometry.point_fusion import concatenate, voxel_merge

    features = feature_maps[example]
    if features is None:
        raise ConfigError("export.query: the model renders no feature map (neither a feature field nor a semantic "
                          "embedding) to query")
    asked = query_asked(query, scene)
    threshold = float(query.threshold)
    where = {key: asked[key] for key in ("pixel", "box") if key in asked}
    embedding = example_embedding(features.float().cpu(), image_size=(scene.height, scene.width),
                                  **{key: tuple(value) for key, value in where.items()})
    record: dict[str, Any] = {**where, "frame": example, "threshold": threshold, "features": source,
                              "channels": int(features.shape[0])}
    gaussians = None
    matrix = gaussian_feature_matrix(splats) if splats is not None else None
    if matrix is not None:
        selected = select_gaussians(matrix.float().cpu(), embedding, threshold)
        gaussians = (splats, selected, relevancy(matrix.float().cpu(), embedding))
        record["gaussians_selected"] = int(selected.sum())
    elif splats is not None:
        record["gaussians_note"] = "the model's Gaussians carry no features (no feature field): no Gaussian selection"
    chosen = []
    for index, cloud, keep, (rows, cols) in zip(indices, clouds, keeps, grids):
        grid = similarity_map(feature_maps[index].float().cpu(), embedding)[None, None]
        similarity = torch.nn.functional.interpolate(grid, size=(rows, cols), mode="nearest").reshape(-1) \
            if grid.shape[-2] <= rows else torch.nn.functional.adaptive_avg_pool2d(grid, (rows, cols)).reshape(-1)
        chosen.append(cloud_subset(cloud, keep & (similarity >= threshold)))
    points = voxel_merge(concatenate(chosen), voxel)
    record["points_selected"] = len(points)
    return {"gaussians": gaussians if gaussians is not None and bool(gaussians[1].any()) else None,
            "points": points if len(points) else None, "record": record}


def selection_writes(selection: dict[str, Any], result: dict[str, Any]) -> list[tuple[str, Write]]:
    """The staged writes of a query's selections (``selection_gaussians.ply``, ``selection_points.ply``), noting in
    ``result["query"]`` what was not written."""
    from gpnerf_core.features.queries import write_gaussian_selection, write_point_selection

    comment = (f"gpnerf-core query selection in scene {result['scene']} from {result['checkpoint']}: "
               f"{ {k: v for k, v in result['query'].items() if k in ('pixel', 'box', 'frame', 'threshold')} }",)
    writes: list[tuple[str, Write]] = []
    if selection["gaussians"] is not None:
        splats, selected, scores = selection["gaussians"]
        writes.append(("selection_gaussians.ply", partial(write_gaussian_selection, scene=splats, selected=selected,
                                                          scores=scores, comments=comment)))
    points = selection["points"]
    if points is not None:
        writes.append(("selection_points.ply", partial(write_point_selection, xyz=points.xyz, rgb=points.rgb,
                                                       selected=torch.ones(len(points), dtype=torch.bool),
                                                       comments=comment)))
    if not writes:
        result["query"]["note"] = "nothing is as similar as the threshold to the example: no selection written"
    return writes


def scene_gaussians(model: Any, given: Any, scene: Any, owners: Any, name: str) -> Any:
    """The Gaussians a Gaussian family renders ``scene`` from (a feed-forward family's from the source views of the
    first exported frame, ``given``), checked finite; None for a family without Gaussians."""
    from gpnerf_core.errors import NonFiniteError, PluginError
    from gpnerf_core.geometry.gaussians.scene import scene_problem
    from gpnerf_core.runtime.finite import all_finite

    if not model.capabilities.gaussians:
        return None
    with torch.no_grad():
        splats = model.scene_gaussians(given.sources, near=scene.near, far=scene.far, features=given.features)
    output = model.semantic_output
    problem = scene_problem(splats, output.num_outputs if output is not None else None)
    if problem is not None:
        raise PluginError(f"export: scene {name!r}: the Gaussians of {family_where(owners.get('colour', 'model'))}: "
                          f"{problem}; nothing was written")
    for field in ("means", "scales", "rotations", "opacities", "harmonics"):
        if not all_finite(getattr(splats, field)):
            raise NonFiniteError(f"export: scene {name!r}: the {owners.get('colour', 'model')} gave NaN or Inf in its "
                                 f"Gaussians' {field}; nothing was written")
    return splats


def family_where(owner: str) -> str:
    """``model 'x' (plugin <module>, <distribution> <version>)`` for the model ``owner`` names (``model 'x'``): the
    registry's record of it, so a plugin's fault names the plugin; ``owner`` itself when the registry has none."""
    from gpnerf_core.registry.components import get_registry

    family = owner.removeprefix("model ").strip("'")
    try:
        return get_registry().get("model", family).where
    except Exception:  # noqa: BLE001 - a message's detail; the fault itself is raised by the caller
        return owner


def rendered_points(prediction: Any, camera: Any, output: Any) -> tuple[Any, Any]:
    """The rendered grid of one view as a ``DepthView`` and a ``PointCloud`` (one point per cell, row-major)."""
    from gpnerf_core.evaluation.instances import slot_predictions
    from gpnerf_core.geometry.point_fusion import PointCloud, backproject, rendered_view
    from gpnerf_core.interfaces.head import Predicts

    view = rendered_view(prediction, camera)
    rgb = prediction.rgb.detach().float().cpu().clamp(0, 1).reshape(-1, 3)
    if prediction.logits is None or output is None:
        label = torch.full((rgb.shape[0],), -1, dtype=torch.long)
    else:
        cells = cell_scores(prediction)
        if output.predicts is Predicts.INSTANCES:
            label = slot_predictions(cells, output.slot_activation)[0].reshape(-1).long()
        else:
            label = cells.argmax(dim=0).reshape(-1)
    return view, PointCloud(backproject(view), rgb, label)


def cell_depth(depth: torch.Tensor, stride: int, grid: tuple[int, int]) -> torch.Tensor:
    """A frame's depth ``[H, W]`` (0 = unknown) as the mean of each rendered cell's known pixels, ``grid``-shaped
    (0 where the cell has none)."""
    known = (depth > 0).float()[None, None]
    total = torch.nn.functional.avg_pool2d((depth * known[0, 0])[None, None], stride)[0, 0]
    share = torch.nn.functional.avg_pool2d(known, stride)[0, 0]
    mean = torch.where(share > 0, total / share.clamp_min(1e-12), torch.zeros_like(total))
    return mean[: grid[0], : grid[1]]


def depth_errors(views: list[Any], sensor: list[torch.Tensor], keeps: list[torch.Tensor]) -> dict[str, Any] | None:
    """How far the rendered depth is from the frames' own depth (where they have it), at the cells of all points and of
    the points kept: median absolute error in metres and the share within 5 cm; None for frames without depth."""
    rendered = torch.cat([view.depth.reshape(-1) for view in views])
    measured = torch.cat([depth.reshape(-1) for depth in sensor])
    kept = torch.cat(keeps)
    known = measured > 0
    if not bool(known.any()):
        return None

    def summary(mask: torch.Tensor) -> dict[str, Any]:
        error = (rendered - measured)[mask & known].abs()
        if error.numel() == 0:
            return {"points": 0, "median": None, "within_5cm": None}
        return {"points": int(error.numel()), "median": round(float(error.median()), 4),
                "within_5cm": round(float((error <= 0.05).float().mean()), 4)}

    return {"all": summary(torch.ones_like(kept)), "kept": summary(kept)}


def cloud_subset(cloud: Any, keep: torch.Tensor) -> Any:
    from gpnerf_core.geometry.point_fusion import PointCloud

    return PointCloud(cloud.xyz[keep], cloud.rgb[keep], cloud.label[keep])


def _result(cfg: DictConfig, loaded: Any, components: Any, scene: str, indices: list[int], stride: int,
            rendered: int, agreed: int, written: int, seconds: float) -> dict[str, Any]:
    from gpnerf_core.interfaces.head import Predicts

    output = components.model.semantic_output
    labels = None if output is None else ("instances" if output.predicts is Predicts.INSTANCES else "classes")
    settings = cfg.export
    return {
        "checkpoint": str(loaded.trained.path), "scene": scene, "frames": indices, "stride": stride,
        "min_views": int(settings.min_views), "tolerance": float(settings.tolerance), "voxel": float(settings.voxel),
        "points_rendered": rendered, "points_agreed": agreed, "points_written": written, "labels": labels,
        "classes": list(components.classes.names) if labels == "classes" else None,
        "outputs": ["points.ply", *(["points_labels.ply"] if labels else []),
                    *(["legend.png"] if labels == "classes" and components.classes.names else []), "export.json"],
        "seconds": round(seconds, 3),
    }


def _writes(cloud: Any, result: dict[str, Any], components: Any, splats: Any = None) -> list[tuple[str, Write]]:
    from gpnerf_core.evaluation import visualize as vis
    from gpnerf_core.runtime.io import atomic_write_json
    from gpnerf_core.runtime.ply import write_ply

    xyz = cloud.xyz.numpy().astype(np.float32)
    label = cloud.label.numpy().astype(np.int32)
    comment = (f"gpnerf-core export of scene {result['scene']} from {result['checkpoint']}",)

    def columns(colours: np.ndarray) -> dict[str, np.ndarray]:
        return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": colours[:, 0], "green": colours[:, 1],
                "blue": colours[:, 2], "label": label}

    writes: list[tuple[str, Write]] = []
    if "points.ply" in result["outputs"]:
        rgb = (cloud.rgb.numpy() * 255).round().astype(np.uint8)
        writes.append(("points.ply", partial(write_ply, columns=columns(rgb), comments=comment)))
    if "points_labels.ply" in result["outputs"]:
        if result["labels"] == "instances":
            label_colours = vis.colorize_instances(cloud.label[None]).reshape(-1, 3)
        else:
            label_colours = vis.colorize_labels(cloud.label[None], components.classes.num_classes).reshape(-1, 3)
        writes.append(("points_labels.ply", partial(write_ply, columns=columns(label_colours.astype(np.uint8)),
                                                    comments=comment)))
    if splats is not None:
        splat_comment = (f"gpnerf-core 3D Gaussian splatting export of scene {result['scene']} from "
                         f"{result['checkpoint']}: Gaussians of source frames {result['gaussians']['source_frames']}",)
        writes.append(("gaussians.ply", partial(write_ply, columns=splats.ply_columns(), comments=splat_comment)))
    if "legend.png" in result["outputs"]:
        writes.append(("legend.png", partial(vis.save_image, image=vis.class_legend(components.classes.names))))
    writes.append(("export.json", partial(atomic_write_json, obj=result)))
    return writes
