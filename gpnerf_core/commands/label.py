"""``python -m gpnerf_core label checkpoint=<.pt> [dataset=...] [label.scene=<name>] out_dir=<folder>``.

A trained model's labels of every frame of one scene: each frame rendered at its own camera from the training frames
but itself (as evaluation does; a per-scene model from its own parameters), its per-pixel scores' argmax written as a
class-id PNG at the dataset's image size. They are the targets a per-scene model distils into 3D on a scene that has
no labels of its own (a capture: ``dataset=capture dataset.labels_from=<folder>``, docs/datasets/capture.md): the
label-free path from a video and a trained generalizable model to a semantic 3D scene. Writes into the run folder, all
or none (staged):

- ``labels/<frame index, 5 digits>.png``: 8-bit (16-bit above 255 classes) class ids, one per frame in scene order;
- ``labels.json``: the scene, its frame count and image size, the class names and ignore index, the checkpoint, the
  model, the source views per frame and the seconds taken.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import claim_run_folder
from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.runtime.staging import Write, write_staged

STAGING_PREFIX = ".label.partial-"
"""The folder inside the run folder that ``label`` writes into before renaming its outputs into place."""
LABELS_FOLDER = "labels"
LABELS_FILE = "labels.json"


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(label_task, argv, "label")


def label_file(index: int) -> str:
    """Where frame ``index``'s labels are, inside the run folder."""
    return f"{LABELS_FOLDER}/{index:05d}.png"


def _write_png(path: Any, labels: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(labels).save(path, format="PNG")


@job
def label_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from functools import partial

    from tqdm import tqdm

    from gpnerf_core.data.dataset import chosen_scene
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.interfaces.head import Predicts
    from gpnerf_core.model.view_inputs import view_inputs
    from gpnerf_core.runtime.io import atomic_write_json

    loaded = open_trained(handover.trained, cfg=cfg, command="label", validated=handover.validated,
                          device=dist.device)
    components = loaded.components
    model = components.model.eval()
    output = model.semantic_output
    if output is None or output.predicts is not Predicts.CLASSES:
        what = "no semantic output" if output is None else "instance slots, not classes"
        raise ConfigError(f"label writes class ids, and model {cfg.model.name!r} of {loaded.trained.path} predicts "
                          f"{what}; expected a checkpoint whose model predicts classes")
    frames = FrameCache(components.dataset, dist.device)
    name = chosen_scene(components.dataset, "label.scene", str(cfg.label.scene), loaded.fitted)
    scene = frames.scene(name)
    owners = model.hooks.output_owners(component_names(cfg))
    classes = components.classes
    dtype = np.uint8 if classes.num_classes <= 255 else np.uint16
    folder, _ = claim_run_folder(cfg, dist, resuming=False)
    with folder:
        for note in loaded.notes:
            print(f"note: {note}", file=sys.stderr)
        started = time.perf_counter()
        writes: list[tuple[str, Write]] = []
        for index in tqdm(range(scene.num_frames), desc="label", unit="frame", file=sys.stderr, dynamic_ncols=True):
            camera = frames.camera(scene, frames.frame(scene, index))
            given = view_inputs(model, frames, components.view_selector, scene, camera.c2w,
                                int(cfg.model.num_source_views), exclude=index)
            with torch.no_grad():
                prediction = model.predict(camera, given.sources, stride=0, chunk_rays=int(cfg.eval.chunk_rays),
                                           features=given.features)
            prediction.check_finite(owners, f"label: scene {name!r} frame {index}")
            labels = prediction.logits[0].argmax(dim=0).to("cpu", torch.int64).numpy().astype(dtype)
            writes.append((label_file(index), partial(_write_png, labels=labels)))
        result = {
            "scene": name, "frames": scene.num_frames, "size": [scene.height, scene.width],
            "classes": list(classes.names), "ignore_index": int(components.dataset.ignore_index),
            "checkpoint": str(loaded.trained.path), "model": str(cfg.model.name),
            "source_views": int(cfg.model.num_source_views) if model.capabilities.generalizable else 0,
            "seconds": round(time.perf_counter() - started, 3),
        }
        writes.append((LABELS_FILE, partial(atomic_write_json, obj=result)))
        write_staged(folder.path, writes, STAGING_PREFIX)
        print(f"labelled {scene.num_frames} frames of {name} with {cfg.model.name} to {folder.path / LABELS_FOLDER}")
    return result
