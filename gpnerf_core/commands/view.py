"""``python -m gpnerf_core view checkpoint=<.pt> [dataset and scene overrides] [view.port=8080] [view.host=127.0.0.1]``.

Serves an interactive web viewer of a trained model (``gpnerf_core.tools.viewer``): the scene's cameras and depth points,
and the model's novel view for the browser's camera (RGB, depth, semantic classes or instances, PCA of the rendered
features), rendered progressively. Binds 127.0.0.1 unless ``view.host`` says otherwise; prints the URL; serves until
Ctrl-C or SIGTERM (exit code 130 or 143, one line), also when started in the background by a script (which leaves SIGINT
ignored: the viewer installs its own handlers). Writes nothing: the folder Hydra creates for the job is removed again
when it stays empty.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from omegaconf import DictConfig

from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import GpnerfError
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import run_dir
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.runtime.signals import Terminated


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(view_task, argv, "view")


@job
def view_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    with _stopped_by_signals():
        return _serve(cfg, dist, handover)


@contextlib.contextmanager
def _stopped_by_signals() -> Iterator[None]:
    """For the viewer's lifetime SIGINT raises ``KeyboardInterrupt`` and SIGTERM ``Terminated``, whatever the process
    inherited: started in the background by a script, it inherits SIGINT ignored, which Python leaves so."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


def _serve(cfg: DictConfig, dist: Distributed, handover: Handover) -> dict[str, Any]:
    from gpnerf_core.model.feature_cache import SourceFeatureCache
    from gpnerf_core.data.dataset import chosen_scene, shown_scenes
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.tools.viewer.server import ViewerOptions, ViewerServer, check_port_free, serve_until_stopped
    from gpnerf_core.tools.viewer.renderer import SceneRenderer, preview_of

    try:
        _remove_empty_job_folder(cfg)
        host, port = str(cfg.view.host), int(cfg.view.port)
        check_port_free(host, port)  # before loading the model: a port in use is refused at once
        preview = preview_of(cfg.view)
        loaded = open_trained(handover.trained, cfg=cfg, command="view", validated=handover.validated,
                              device=dist.device)
        components = loaded.components
        for note in loaded.notes:
            print(f"note: {note}", file=sys.stderr)
        model = components.model.eval()
        scenes = shown_scenes(components.dataset, loaded.fitted)
        first = chosen_scene(components.dataset, "view.scene", str(cfg.view.scene), loaded.fitted)
        budget = float(cfg.view.feature_cache_mb)
        renderer = SceneRenderer(
            model, FrameCache(components.dataset, dist.device), components.view_selector,
            num_classes=components.classes.num_classes, chunk_rays=int(cfg.eval.chunk_rays),
            default_source_views=int(cfg.model.num_source_views),
            feature_cache=SourceFeatureCache(budget) if budget > 0 else None, preview=preview,
        )
        output = model.semantic_output
        semantic = output is not None and output.predicts is Predicts.CLASSES
        options = ViewerOptions(
            host=host, port=port, scene=first, scenes=tuple(scenes), stride=int(cfg.view.stride),
            preview_stride=int(cfg.view.preview_stride), source_views=int(cfg.view.source_views),
            class_names=tuple(components.classes.names) if semantic else (),
            text_encoder=_text_encoder(components),
        )
        server = ViewerServer(renderer, options).start()
        serve_until_stopped(server, threading.Event())
        return {"url": server.url if server.server else f"http://{host}:{port}", "frames": server.frames_delivered}
    finally:
        _remove_empty_job_folder(cfg)


def _text_encoder(components: Any) -> Any:
    """``text -> [C]`` query embedding from the feature provider of the model's feature field, where it has a text
    encoder (``FeatureProvider.text_encoder``); None otherwise (the viewer shows no text box)."""
    from functools import partial

    from gpnerf_core.features.queries import text_embedding

    field = getattr(components, "feature_field", None)
    provider = getattr(field, "provider", None)
    if provider is None or not bool(getattr(provider, "text_encoder", False)):
        return None
    return partial(text_embedding, provider)


def _remove_empty_job_folder(cfg: DictConfig) -> None:
    """The viewer writes no file: the job folder Hydra made before the task ran goes again if it is empty (a folder the
    user named with ``out_dir`` is left alone)."""
    if cfg.out_dir:
        return
    try:
        folder = run_dir(cfg)
    except GpnerfError:
        return
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()
