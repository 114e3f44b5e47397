"""A trained model's labels of every frame of one scene, as ``label`` writes them and a dataset's ``labels_from``
reads them (``labels/<frame index, 5 digits>.png`` class ids and ``labels.json``): the targets of a per-scene model on
a scene without labels of its own (``label``, and ``fit checkpoint=...`` on an unlabelled capture)."""

from __future__ import annotations

import sys
from functools import partial
from typing import Any

import numpy as np
import torch

from gpnerf_core.runtime.staging import Write

LABELS_FOLDER = "labels"
LABELS_FILE = "labels.json"


def label_file(index: int) -> str:
    """Where frame ``index``'s labels are, inside the run folder."""
    return f"{LABELS_FOLDER}/{index:05d}.png"


def _write_png(path: Any, labels: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(labels).save(path, format="PNG")


def frame_label_writes(model: Any, frames: Any, selector: Any, scene: Any, num_views: int, chunk_rays: int,
                       owners: Any, dtype: Any) -> list[tuple[str, Write]]:
    """Each frame of ``scene`` rendered at its own camera from the training frames but itself (``predict`` at stride 0),
    its per-pixel scores' argmax as a class-id PNG to write (``label_file``); checked finite, naming the frame."""
    from tqdm import tqdm

    from gpnerf_core.model.view_inputs import view_inputs

    writes: list[tuple[str, Write]] = []
    for index in tqdm(range(scene.num_frames), desc="label", unit="frame", file=sys.stderr, dynamic_ncols=True):
        camera = frames.camera(scene, frames.frame(scene, index))
        given = view_inputs(model, frames, selector, scene, camera.c2w, num_views, exclude=index)
        with torch.no_grad():
            prediction = model.predict(camera, given.sources, stride=0, chunk_rays=chunk_rays, features=given.features)
        prediction.check_finite(owners, f"label: scene {scene.name!r} frame {index}")
        labels = prediction.logits[0].argmax(dim=0).to("cpu", torch.int64).numpy().astype(dtype)
        writes.append((label_file(index), partial(_write_png, labels=labels)))
    return writes


def labels_record(scene: Any, classes: Any, ignore_index: int, checkpoint: str, model: str, source_views: int,
                  seconds: float) -> dict[str, Any]:
    """``labels.json``: what a dataset's ``labels_from`` reads of the labels (scene, frames, size, classes)."""
    return {"scene": scene.name, "frames": scene.num_frames, "size": [scene.height, scene.width],
            "classes": list(classes.names), "ignore_index": int(ignore_index), "checkpoint": checkpoint,
            "model": model, "source_views": source_views, "seconds": round(seconds, 3)}


