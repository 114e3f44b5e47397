"""How long the viewer takes for one camera: ``python -m gpnerf_core.tools.viewer.timing [--repeats=3] [overrides]``.

Builds the model of the given config (its weights do not change the time of a fixed-size model), or with
``checkpoint=<pt>`` the checkpoint's model with its weights, opened as ``view`` opens it (``open_trained``: its config,
the overrides after it, its model settings restored: the size of a model that grows while it trains, per-scene
Gaussians, is its checkpoint's), then, for a camera at a training frame of the first scene (a per-scene model's own),
times what the viewer does when a camera stops: the preview at ``view.preview_stride`` (``view.preview_samples`` per
ray around ``view.preview_depth_source``'s depth; 0 = as the full frame) and the full frame at ``view.stride``, each for
a camera whose sources are not encoded yet (cold) and again with the feature cache holding them (warm, as while the
camera moves among the same sources), and a query on the full frame the viewer keeps (``query_s``: a click at the
view's centre made the query, its relevancy map blended over the picture, no render; ``tools/viewer/query.py``).
Prints one JSON object (seconds, the image size, threads and device, and the process's CPU user and system seconds
and minor page faults over the timed renders: ``keep_freed_memory=false`` shows what glibc's defaults cost)."""

from __future__ import annotations

import json
import math
import resource
import sys
import time

import torch

from gpnerf_core.interfaces.model import parameter_counts


def measure(overrides: list[str], repeats: int = 3) -> dict[str, object]:
    from gpnerf_core.model.build import build_components
    from gpnerf_core.config.compose import compose
    from gpnerf_core.engine.setup import setup_process
    from gpnerf_core.data.dataset import shown_scenes
    from gpnerf_core.model.feature_cache import SourceFeatureCache
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.tools.viewer.camera import vertical_fov, viser_pose
    from gpnerf_core.tools.viewer.renderer import SceneRenderer, ViewRequest, preview_of

    given = [o for o in overrides if o.startswith("checkpoint=")]
    fitted = None
    if given:  # the trained model as `view` opens it: its settings restored, its (trained) weights, on the CPU
        from gpnerf_core.engine.opening import open_trained
        from gpnerf_core.model.trained import load_trained

        opened = open_trained(load_trained(given[-1].split("=", 1)[1]), [o for o in overrides if o not in given],
                              command="timing", weights="trained", device=torch.device("cpu"))
        cfg, components, fitted = opened.cfg, opened.components, opened.fitted
    else:
        cfg = compose(overrides)
        setup_process(cfg)
        components = build_components(cfg)
    model = components.model.eval()
    scenes = shown_scenes(components.dataset, fitted)
    renderer = SceneRenderer(model, FrameCache(components.dataset, torch.device("cpu")), components.view_selector,
                             num_classes=components.classes.num_classes, chunk_rays=int(cfg.eval.chunk_rays),
                             default_source_views=int(cfg.model.num_source_views),
                             feature_cache=SourceFeatureCache(float(cfg.view.feature_cache_mb)),
                             preview=preview_of(cfg.view))
    scene = renderer.frames.scene(scenes[0])
    index = scene.train_frames[0]
    wxyz, position = viser_pose(scene.c2w[index])
    request = ViewRequest(scene=scene.name, wxyz=tuple(wxyz), position=tuple(position),
                          fov=vertical_fov(scene.intrinsics[index], scene.height), aspect=scene.width / scene.height,
                          source_views=int(cfg.view.source_views), stride=int(cfg.view.stride),
                          preview_stride=int(cfg.view.preview_stride))
    camera = renderer.camera(request, math.lcm(request.stride, request.preview_stride))
    result: dict[str, object] = {"scene": scene.name, "image": [camera.height, camera.width],
                                 "stride": request.stride, "preview_stride": request.preview_stride,
                                 "preview_samples": int(cfg.view.preview_samples),
                                 "preview_depth_source": str(cfg.view.preview_depth_source),
                                 "threads": torch.get_num_threads(), "device": "cpu",
                                 "parameters": parameter_counts(model)["total"]}
    usage = resource.getrusage(resource.RUSAGE_SELF)
    for stage, stride in (("preview", request.preview_stride), ("full", request.stride)):
        cold = []
        for _ in range(repeats):
            renderer.feature_cache.clear()
            began = time.perf_counter()
            renderer.render(scene.name, camera, request.source_views, stride, stage)
            cold.append(time.perf_counter() - began)
        began = time.perf_counter()
        for _ in range(repeats):
            view = renderer.render(scene.name, camera, request.source_views, stride, stage)
        result[f"{stage}_s_cold"] = round(min(cold), 4)
        result[f"{stage}_s_warm"] = round((time.perf_counter() - began) / repeats, 4)
    after = resource.getrusage(resource.RUSAGE_SELF)
    result.update(query_timing(view, repeats))
    result.update(cpu_user_s=round(after.ru_utime - usage.ru_utime, 2),
                  cpu_system_s=round(after.ru_stime - usage.ru_stime, 2),
                  minor_page_faults=after.ru_minflt - usage.ru_minflt, peak_resident_mb=after.ru_maxrss // 1024)
    return result


def query_timing(view: object, repeats: int) -> dict[str, object]:
    """Seconds a query takes on the kept full frame ``view`` (the click's embedding, the similarity and the blended
    picture; the mean of ``repeats``), which feature map it reads and its channels; ``query_s`` None with the reason
    for a model without a feature map."""
    from gpnerf_core.errors import ConfigError
    from gpnerf_core.features.queries import prediction_feature_source
    from gpnerf_core.tools.viewer.query import answer, click_query

    prediction = view.prediction
    try:
        began = time.perf_counter()
        for _ in range(repeats):
            answer(prediction, view.layers["rgb"], click_query(prediction, (0.5, 0.5)), 0.5)
    except ConfigError as exc:
        return {"query_s": None, "query_note": str(exc)}
    source = prediction_feature_source(prediction)
    features = prediction.features if source == "feature_field" else prediction.semantic
    return {"query_s": round((time.perf_counter() - began) / repeats, 5), "query_features": source,
            "query_grid": [int(features.shape[0]), int(features.shape[1]), int(features.shape[2])]}


if __name__ == "__main__":
    arguments = sys.argv[1:]
    repeats = 3
    if arguments and arguments[0].startswith("--repeats="):
        value = arguments.pop(0).split("=", 1)[1]
        if not value.isdigit() or int(value) < 1:
            print(f"error: --repeats={value}: expected an integer >= 1 (renders timed per stage)", file=sys.stderr)
            sys.exit(2)
        repeats = int(value)
    print(json.dumps(measure(arguments, repeats=repeats), indent=1))
