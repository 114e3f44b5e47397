"""``python -m gpnerf_core render checkpoint=<.pt> [render.scene=...] [render.path=interpolate|spiral] [render.frames=N]``.

Renders a novel-view trajectory of one scene with a trained model: RGB, depth and the head's semantic classes side by
side per frame, written as PNG frames, an MP4 (the ffmpeg that imageio-ffmpeg ships) and a GIF (Pillow) in the run
folder, both at ``render.fps`` (an integer in [1, 50]: a GIF's frame delay is whole centiseconds, so its delays
alternate to keep that rate), with the classes' colour legend (``legend.png``; ``render.json`` names them and records
the fps). Every output is written into a staging folder inside the run folder and renamed into place at the end, so a
failure (a full disk) leaves none of them, half-written or whole. The classes are the model's: the dataset's, or the
checkpoint's on a dataset without a class list (a capture without labels). The trajectories are
``gpnerf_core.geometry.trajectories``'; each rendered pose takes its source views from the scene's training frames with
the configured view selector.
"""

from __future__ import annotations

import errno
import math
import subprocess
import sys
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.model.view_inputs import view_inputs
from gpnerf_core.geometry.trajectories import trajectory
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import claim_run_folder
from gpnerf_core.runtime.staging import Write, write_staged


MAX_FPS = 50
"""The most frames per second a GIF plays: its frame delay is whole centiseconds, and players show a delay under 2 cs
as 10 cs."""
STAGING_PREFIX = ".render.partial-"
"""The folder inside the run folder that a render writes into before renaming its outputs into place."""


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(render_task, argv, "render")


def checked_fps(value: Any) -> int:
    """``render.fps`` as an int, or one ``ConfigError`` naming the key and the range."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_FPS:
        raise ConfigError(f"render.fps={value!r}: expected an integer in [1, {MAX_FPS}] (frames per second of the MP4 "
                          f"and the GIF; a GIF plays at most {MAX_FPS})")
    return value


@job
def render_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from tqdm import tqdm

    from gpnerf_core.evaluation import visualize as vis
    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.evaluation.pictures import prediction_layers
    from gpnerf_core.data.dataset import chosen_scene
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.interfaces.head import Predicts

    fps = checked_fps(cfg.render.fps)
    budget = float(cfg.render.feature_cache_mb)
    if budget < 0:
        raise ConfigError(f"render.feature_cache_mb={budget}: expected megabytes >= 0 (0 = no cache)")
    loaded = open_trained(handover.trained, cfg=cfg, command="render", validated=handover.validated,
                          device=dist.device)
    checkpoint, notes, components = loaded.trained.path, loaded.notes, loaded.components
    model = components.model.eval()
    classes = components.classes
    output = model.semantic_output
    semantic = output is not None and output.predicts is Predicts.CLASSES
    frames = FrameCache(components.dataset, dist.device)
    feature_cache = SourceFeatureCache(budget) if budget > 0 else None
    name = chosen_scene(components.dataset, "render.scene", str(cfg.render.scene), loaded.fitted)
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
            prediction.check_finite(model.hooks.output_owners(component_names(cfg)), f"render frame {len(pictures)} of {name!r}")
            layers = prediction_layers(prediction, scene.near, scene.far, output, classes.num_classes, full_size=True)
            shown = [name for name in ("rgb", "depth", "semantic", "instances") if name in layers]
            pictures.append(vis.side_by_side([layers[name] for name in shown], shown))
        render_seconds = time.perf_counter() - started
        legend = vis.class_legend(classes.names) if semantic and classes.names else None
        outputs = ["trajectory.mp4", "trajectory.gif", "frames/", *(["legend.png"] if legend is not None else [])]
        result = {"checkpoint": str(checkpoint), "scene": name, "path": str(cfg.render.path), "frames": len(pictures),
                  "fps": fps, "outputs": outputs, "classes": list(classes.names) if semantic else None,
                  "classes_from": classes.source if semantic else None,
                  "render_seconds": round(render_seconds, 3),
                  "feature_cache": {"budget_mb": budget, "frames_encoded": feature_cache.stats.misses,
                                    "frames_reused": feature_cache.stats.hits} if feature_cache is not None else None}
        _write_outputs(run_dir, pictures, fps, legend, result)
        print(f"rendered {len(pictures)} frames of {name} at {fps} fps to {run_dir} ({', '.join(outputs)})")
    return result


def _write_outputs(run_dir: Path, pictures: list[np.ndarray], fps: int, legend: np.ndarray | None,
                   result: dict[str, Any]) -> None:
    """Write the frames, the MP4, the GIF, the legend and ``render.json`` into a staging folder inside ``run_dir``,
    then rename each into place: whatever fails (a full disk, an interruption) leaves none of them behind."""
    from gpnerf_core.evaluation import visualize as vis
    from gpnerf_core.runtime.io import atomic_write_json

    writes: list[tuple[str, Write]] = [
        *((f"frames/{index:04d}.png", partial(vis.save_image, image=picture)) for index, picture in enumerate(pictures)),
        ("trajectory.mp4", partial(write_mp4, pictures=pictures, fps=fps)),
        ("trajectory.gif", partial(write_gif, pictures=pictures, fps=fps)),
        *([("legend.png", partial(vis.save_image, image=legend))] if legend is not None else []),
        ("render.json", partial(atomic_write_json, obj=result)),
    ]
    write_staged(run_dir, writes, STAGING_PREFIX)


def gif_delays_ms(frames: int, fps: int) -> list[int]:
    """Per-frame delays (ms, whole centiseconds: GIF's unit) whose running sum stays within 5 ms of ``i / fps``: a
    GIF at exactly ``fps`` over the trajectory where one fixed delay would round the rate (30 fps -> 33.3)."""
    ends = [math.floor(100 * (i + 1) / fps + 0.5) for i in range(frames)]
    return [10 * (end - start) for start, end in zip([0, *ends[:-1]], ends)]


def write_gif(path: Path, pictures: list[np.ndarray], fps: int) -> None:
    """A looping GIF of ``pictures`` (uint8 ``[H, W, 3]``) at ``fps``."""
    from PIL import Image

    images = [Image.fromarray(picture) for picture in pictures]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=gif_delays_ms(len(images), fps), loop=0)


def write_mp4(path: Path, pictures: list[np.ndarray], fps: int) -> None:
    """An H.264 MP4 of ``pictures`` (uint8 ``[H, W, 3]``, cropped to even sides for yuv420p) at ``fps``, encoded by
    imageio-ffmpeg's ffmpeg with its messages captured: a failure is one ``OSError`` (ENOSPC for a full disk) or
    ``GpnerfError`` with ffmpeg's reason, never ffmpeg's output on the terminal."""
    import imageio_ffmpeg

    even = [np.ascontiguousarray(p[: p.shape[0] // 2 * 2, : p.shape[1] // 2 * 2]) for p in pictures]
    height, width = even[0].shape[:2]
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-hide_banner", "-nostdin", "-loglevel", "error",
               "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}", "-r", str(fps), "-i", "pipe:0",
               "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-r", str(fps), "-f", "mp4", str(path)]
    process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               bufsize=0)
    messages: list[bytes] = []
    reader = threading.Thread(target=lambda: messages.append(process.stderr.read()), daemon=True)
    reader.start()
    try:
        send_frames(process.stdin, even)
    except BrokenPipeError:
        pass  # ffmpeg stopped early: its exit code and messages say why
    except BaseException:
        process.kill()  # interrupted: the encoder stops too
        raise
    finally:
        process.stdin.close()
        code = process.wait()
        reader.join()
    if code != 0:
        raise _ffmpeg_error(path, code, b"".join(messages).decode(errors="replace"))


def send_frames(stream: Any, pictures: list[np.ndarray]) -> None:
    """Feed raw RGB frames to the encoder's unbuffered stdin (a pipe write may take part of a frame)."""
    for picture in pictures:
        data = memoryview(picture.tobytes())
        while data:
            data = data[stream.write(data):]


def _ffmpeg_error(path: Path, code: int, messages: str) -> Exception:
    """ffmpeg's failure as one error: an ``OSError`` naming ``path`` where the disk is full, else its last message."""
    lines = [line.strip() for line in messages.splitlines() if line.strip()]
    reason = lines[-1] if lines else f"exit code {code}"
    if "No space left on device" in messages:
        return OSError(errno.ENOSPC, "No space left on device", str(path))
    return GpnerfError(f"ffmpeg could not encode the video ({reason[:200]})")
