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
from omegaconf import DictConfig

from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import claim_run_folder
from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.model.predicted_labels import LABELS_FILE, LABELS_FOLDER, frame_label_writes, labels_record
from gpnerf_core.runtime.staging import write_staged

STAGING_PREFIX = ".label.partial-"
"""The folder inside the run folder that ``label`` writes into before renaming its outputs into place."""


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(label_task, argv, "label")


@job
def label_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from functools import partial

    from gpnerf_core.data.dataset import chosen_scene
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.interfaces.head import Predicts
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
        writes = frame_label_writes(model, frames, components.view_selector, scene, int(cfg.model.num_source_views),
                                    int(cfg.eval.chunk_rays), owners, dtype)
        result = labels_record(scene, classes, int(components.dataset.ignore_index), str(loaded.trained.path),
                               str(cfg.model.name),
                               int(cfg.model.num_source_views) if model.capabilities.generalizable else 0,
                               time.perf_counter() - started)
        writes.append((LABELS_FILE, partial(atomic_write_json, obj=result)))
        write_staged(folder.path, writes, STAGING_PREFIX)
        print(f"labelled {scene.num_frames} frames of {name} with {cfg.model.name} to {folder.path / LABELS_FOLDER}")
    return result
