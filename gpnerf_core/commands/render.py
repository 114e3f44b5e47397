"""``python -m gpnerf_core render checkpoint=<.pt> [render.scene=...] [render.path=interpolate|spiral] [render.frames=N]``.

Renders a novel-view trajectory of one scene with a trained model: RGB, depth and the head's semantic classes side by
side per frame, written as PNG frames, an MP4 (imageio with its ffmpeg plugin) and a GIF in the run folder, with the
classes' colour legend (``legend.png``; ``render.json`` names them). The classes are the model's: the dataset's, or the
checkpoint's on a dataset without a class list (a capture without labels). The trajectories are
``gpnerf_core.geometry.trajectories``'; each rendered pose takes its source views from the scene's training frames with
the configured view selector.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.model.view_inputs import view_inputs
from gpnerf_core.geometry.trajectories import trajectory
from gpnerf_core.engine.jobs import claim_run_folder, job, launch_from_checkpoint, model_from_checkpoint


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(render_task, argv, "render")


@job
def render_task(cfg: DictConfig, dist: Distributed) -> dict[str, Any]:
    import imageio.v2 as imageio
    from tqdm import tqdm

    from gpnerf_core.evaluation import visualize as vis
    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.evaluation.pictures import prediction_layers
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.interfaces.head import Predicts
    from gpnerf_core.runtime.io import atomic_write_json

    loaded = model_from_checkpoint(cfg, dist, "render", check_scenes=False)
    checkpoint, notes, components = loaded.trained.path, loaded.notes, loaded.components
    model = components.model.eval()
    classes = components.classes
    output = model.semantic_output
    semantic = output is not None and output.predicts is Predicts.CLASSES
    frames = FrameCache(components.dataset, dist.device)
    budget = float(cfg.render.feature_cache_mb)
    if budget < 0:
        raise ConfigError(f"render.feature_cache_mb={budget}: expected megabytes >= 0 (0 = no cache)")
    feature_cache = SourceFeatureCache(budget) if budget > 0 else None
    split_scenes = list(components.dataset.scenes("unseen")) + list(components.dataset.scenes("train"))
    name = str(cfg.render.scene) or (split_scenes[0] if split_scenes else "")
    if name not in split_scenes:
        raise ConfigError(f"render.scene={name!r} is not a scene of this dataset; known: {', '.join(split_scenes)}")
    scene = frames.scene(name)
    poses = trajectory(scene, cfg.render)
    reference = frames.frame(scene, scene.train_frames[0])
    folder, _ = claim_run_folder(cfg, dist, resuming=False)
    run_dir = folder.path
    pictures = []
    with folder:
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
        started = time.perf_counter()
        for pose in tqdm(poses, desc="render", unit="frame", file=sys.stderr, dynamic_ncols=True):
            camera = frames.camera(scene, reference, c2w=pose)
            given = view_inputs(model, frames, components.view_selector, scene, camera.c2w,
                                int(cfg.model.num_source_views), cache=feature_cache)
            prediction = model.predict(camera, given.sources, stride=int(cfg.eval.render_stride),
                                       chunk_rays=int(cfg.eval.chunk_rays), features=given.features)
            prediction.check_finite(model.output_owners(component_names(cfg)), f"render frame {len(pictures)} of {name!r}")
            layers = prediction_layers(prediction, scene.near, scene.far, output, classes.num_classes, full_size=True)
            shown = [name for name in ("rgb", "depth", "semantic", "instances") if name in layers]
            pictures.append(vis.side_by_side([layers[name] for name in shown], shown))
        render_seconds = time.perf_counter() - started
        for index, picture in enumerate(pictures):
            vis.save_image(run_dir / "frames" / f"{index:04d}.png", picture)
        fps = int(cfg.render.fps)
        _write_video(imageio, run_dir / "trajectory.mp4", pictures, fps)
        _write_video(imageio, run_dir / "trajectory.gif", pictures, fps)
        outputs = ["trajectory.mp4", "trajectory.gif", "frames/"]
        if semantic and classes.names:
            vis.save_image(run_dir / "legend.png", vis.class_legend(classes.names))
            outputs.append("legend.png")
        result = {"checkpoint": str(checkpoint), "scene": name, "path": str(cfg.render.path), "frames": len(pictures),
                  "outputs": outputs, "classes": list(classes.names) if semantic else None,
                  "classes_from": classes.source if semantic else None,
                  "render_seconds": round(render_seconds, 3),
                  "feature_cache": {"budget_mb": budget, "frames_encoded": feature_cache.stats.misses,
                                    "frames_reused": feature_cache.stats.hits} if feature_cache is not None else None}
        atomic_write_json(run_dir / "render.json", result)
        print(f"rendered {len(pictures)} frames of {name} to {run_dir} ({', '.join(outputs)})")
    return result


def _write_video(imageio: Any, path: Path, pictures: list[np.ndarray], fps: int) -> None:
    """Write frames to ``path`` through a temporary name, so a failure leaves no half-written video."""
    temporary = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        if path.suffix == ".gif":
            imageio.mimsave(temporary, pictures, duration=1000 / max(fps, 1), loop=0)
        else:
            even = [p[: p.shape[0] // 2 * 2, : p.shape[1] // 2 * 2] for p in pictures]  # yuv420p needs even sides
            imageio.mimsave(temporary, even, fps=fps, codec="libx264", macro_block_size=1)
        temporary.replace(path)
    finally:
        temporary.unlink(missing_ok=True)
