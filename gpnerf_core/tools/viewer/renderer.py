"""Novel views for the viewer: one view rendered with ``GeneralizableNeRF.predict`` and turned into picture layers,
and a background thread that renders each client's latest camera progressively (coarse preview, then the full frame
once the camera rests), dropping work a newer camera made stale."""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Hashable

import numpy as np
import torch
import torch.nn.functional as F

from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.evaluation.pictures import prediction_layers
from gpnerf_core.geometry.gaussians.scene import GaussianScene
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.model.view_inputs import view_inputs
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.interfaces import DepthSource, ViewSelector
from gpnerf_core.interfaces.model import ModelFamily
from gpnerf_core.types import Prediction, Scene, TargetCamera
from gpnerf_core.tools.viewer.camera import view_from_viser

LAYERS = ("rgb", "depth", "semantic", "instances", "features", "error")
"""Picture layers a view may have: ``semantic`` with a class head, ``instances`` with an instance head, ``features``
(PCA of the rendered semantic map) with a semantic field, ``error`` (per-pixel colour error against the real frame)
when the camera sits at a frame of the scene."""
SNAP_DISTANCE = 1e-3
"""A camera within this many metres of a frame's centre ..."""
SNAP_ANGLE = 1e-3
"""... and this many radians of its orientation sits at that frame: it is rendered with the frame's own camera (its
size and intrinsics), without the frame among its sources, and compared with it."""


def frame_at(scene: Scene, c2w: torch.Tensor) -> int | None:
    """The frame of ``scene`` whose pose is ``c2w`` (a camera snapped to it, up to ``SNAP_DISTANCE``/``SNAP_ANGLE``)."""
    pose = c2w.detach().cpu().double()
    distance = (scene.c2w[:, :3, 3].double() - pose[:3, 3]).norm(dim=-1)
    index = int(distance.argmin())
    if float(distance[index]) > SNAP_DISTANCE:
        return None
    relative = scene.c2w[index, :3, :3].double().T @ pose[:3, :3]
    angle = math.acos(max(-1.0, min(1.0, (float(relative.trace()) - 1.0) / 2.0)))
    return index if angle <= SNAP_ANGLE else None


def highlight_class(picture: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """``picture`` ``[H, W, 3]`` uint8 with every pixel whose label (``[H, W]``) is not ``k`` dimmed to a quarter."""
    out = picture.copy()
    other = labels != k
    out[other] = out[other] // 4
    return out


def preview_of(view_cfg: Any) -> tuple[DepthSource, int] | None:
    """The preview's ``(depth source, samples per ray)`` from ``view.preview_samples`` and
    ``view.preview_depth_source`` (None: ``preview_samples=0``).

    Raises:
        ConfigError: a negative or non-integer sample count, or a depth source no plugin registers (the known listed).
    """
    from gpnerf_core.registry.components import get_registry

    samples = view_cfg.preview_samples
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
        raise ConfigError(f"view.preview_samples={samples!r}: expected an integer >= 0 (0 = the preview samples as "
                          "the full frame)")
    if samples == 0:
        return None
    name, known = str(view_cfg.preview_depth_source), get_registry().names("depth_source")
    if name not in known:
        raise ConfigError(f"view.preview_depth_source={name!r}; expected one of: {', '.join(known)}")
    return get_registry().build("depth_source", {"name": name}), samples


@dataclass(frozen=True)
class ViewRequest:
    """What a client asks for: the scene, its viser camera and the render settings.

    Attributes:
        wxyz, position: the viser camera (OpenCV convention, world coordinates); fov: vertical, radians; aspect:
            canvas width / height.
        source_views: source views per render (0 = the model's ``num_source_views``).
        stride, preview_stride: pixels per rendered cell of the full frame and of the preview.
    """

    scene: str
    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov: float
    aspect: float
    source_views: int
    stride: int
    preview_stride: int


@dataclass(frozen=True)
class RenderedView:
    """One rendered view.

    Attributes:
        stage: ``preview`` or ``full``; stride: its render stride.
        layers: name (``LAYERS``) -> ``[h, w, 3]`` uint8 picture (rgb and depth at the render grid, the head's layers
            at the full image size); empty when the render failed.
        sources: the scene frame indices used as source views.
        seconds: wall time of the render; prediction: the model's output (None on failure).
        error: one line when the render failed, else None.
        frame, psnr: the scene frame the camera sits at and the render's PSNR against it (clamped colours), or None.
    """

    stage: str
    stride: int
    layers: dict[str, np.ndarray]
    sources: tuple[int, ...]
    seconds: float
    prediction: Prediction | None = None
    error: str | None = None
    frame: int | None = None
    psnr: float | None = None


class SceneRenderer:
    """Renders novel views of a dataset's scenes with a trained model (synchronous; ``ProgressiveRenderer`` drives it).

    Args:
        model: the model in eval mode, on ``frames.device``.
        frames: the dataset's frame cache.
        selector: picks each view's source views among the scene's training frames (deterministically).
        num_classes, class_names: the head's classes (for the semantic layer).
        chunk_rays: rays rendered at once; default_source_views: source views when a request asks for 0.
        feature_cache: keeps the encoded source maps of the scenes shown (None: every render encodes its sources).
        preview: ``(depth source, samples per ray)`` of the preview stage (``ModelFamily.preview_sampling``); None:
            the preview samples as the full frame.
    """

    def __init__(
        self,
        model: ModelFamily,
        frames: FrameCache,
        selector: ViewSelector,
        num_classes: int,
        chunk_rays: int,
        default_source_views: int,
        feature_cache: SourceFeatureCache | None = None,
        preview: tuple[DepthSource, int] | None = None,
    ) -> None:
        self.model = model
        self.preview = preview
        self.frames = frames
        self.selector = selector
        self.num_classes = num_classes
        self.chunk_rays = chunk_rays
        self.default_source_views = default_source_views
        self.feature_cache = feature_cache
        self.lock = threading.Lock()  # one render at a time: the model and the frame cache are not thread-safe

    def camera(self, request: ViewRequest, multiple: int) -> TargetCamera:
        """The target camera of ``request`` at the scene's image height."""
        scene = self.frames.scene(request.scene)
        view = view_from_viser(request.wxyz, request.position, request.fov, request.aspect, scene.height, multiple)
        return self.frames.camera(scene, c2w=view.c2w, intrinsics=view.intrinsics, size=(view.height, view.width))

    def render(self, scene_name: str, camera: TargetCamera, source_views: int, stride: int, stage: str) -> RenderedView:
        """Render ``camera`` in scene ``scene_name`` at ``stride`` with ``source_views`` sources (0 = default)."""
        began = time.perf_counter()
        with self.lock:
            scene = self.frames.scene(scene_name)
            index = frame_at(scene, camera.c2w)
            frame = self.frames.frame(scene, index) if index is not None else None
            if frame is not None and frame.height % stride == 0 and frame.width % stride == 0:
                camera = self.frames.camera(scene, frame)  # compared pixel for pixel with the real frame
            else:
                index = frame = None
            given = view_inputs(self.model, self.frames, self.selector, scene, camera.c2w,
                                source_views or self.default_source_views, exclude=index, cache=self.feature_cache)
            sampling = (self.model.preview_sampling(*self.preview) if stage == "preview" and self.preview is not None
                        else contextlib.nullcontext())
            with sampling:
                prediction = self.model.predict(camera, given.sources, stride=stride, chunk_rays=self.chunk_rays,
                                                features=given.features)
        layers = self.layers(prediction, scene.near, scene.far)
        psnr = None
        if frame is not None:
            real = F.avg_pool2d(frame.rgb.permute(2, 0, 1)[None], prediction.stride)[0].permute(1, 2, 0)
            rendered = torch.nan_to_num(prediction.rgb.float().cpu()).clamp(0, 1)
            layers["error"] = vis.rgb_error_map(rendered, real)
            psnr = float(-10 * torch.log10(((rendered - real.clamp(0, 1)) ** 2).mean().clamp_min(1e-10)))
        return RenderedView(stage=stage, stride=prediction.stride, layers=layers, sources=given.indices,
                            seconds=time.perf_counter() - began, prediction=prediction, frame=index, psnr=psnr)

    @property
    def draws_gaussians(self) -> bool:
        """The model renders from 3D Gaussians the viewer can draw (``Capabilities.gaussians``)."""
        return self.model.capabilities.gaussians

    @property
    def label_count(self) -> int:
        """The label values a Gaussian may carry (``scene_gaussians``' labels): the classes, or an instance family's
        ``slots + 1`` outputs; 0 without semantic scores."""
        output = self.model.semantic_output
        return 0 if output is None else (output.num_outputs if output.slots is not None else self.num_classes)

    def gaussians(self, scene_name: str, sources: tuple[int, ...]) -> GaussianScene | None:
        """The model's Gaussians of ``scene_name`` for the source frames ``sources`` (a per-scene family's own for
        none), from the feature cache when it holds them; None for a family without Gaussians."""
        if not self.draws_gaussians:
            return None
        with self.lock:
            scene = self.frames.scene(scene_name)
            views = self.frames.source_views(scene, list(sources)) if sources else None
            features = None
            if views is not None and self.feature_cache is not None:
                features = self.feature_cache.for_sources(self.model, scene.name, sources, views, near=scene.near,
                                                          far=scene.far)
            with torch.no_grad():
                return self.model.scene_gaussians(views, near=scene.near, far=scene.far, features=features)

    def layers(self, prediction: Prediction, near: float, far: float) -> dict[str, np.ndarray]:
        """The picture layers of a prediction (``evaluation.pictures``); non-finite values are shown black, never
        raised."""
        return prediction_layers(prediction, near, far, self.model.semantic_output, self.num_classes)


@dataclass
class _Client:
    request: ViewRequest | None = None
    version: int = 0
    submitted: float = 0.0
    done_version: int = 0
    done_stage: str = ""


class ProgressiveRenderer:
    """One background thread rendering every client's latest camera: a preview at the request's ``preview_stride``
    as soon as it can, then the full frame at ``stride`` once no newer camera came for ``rest_s`` seconds.

    A camera that arrives while a view is rendering makes it stale: a stale preview or full frame is dropped, never
    delivered, and a full frame is not started while newer cameras keep coming. Clients are independent: each result
    goes to the client that asked, tagged with the request it answers.

    Args:
        renderer: renders one view.
        deliver: ``(client, request, view)`` called from the render thread with each fresh result (a failed render
            arrives as a view with ``error`` set).
        rest_s: how long a camera must stay still before its full frame starts.
    """

    def __init__(
        self,
        renderer: SceneRenderer,
        deliver: Callable[[Hashable, ViewRequest, RenderedView], None],
        rest_s: float = 0.15,
    ) -> None:
        self.renderer = renderer
        self.deliver = deliver
        self.rest_s = rest_s
        self._clients: dict[Hashable, _Client] = {}
        self._wake = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._loop, name="gpnerf-viewer-render", daemon=True)
        self._thread.start()

    def submit(self, client: Hashable, request: ViewRequest) -> None:
        """The client's camera or settings changed: render ``request`` (replacing any older one of this client)."""
        with self._wake:
            state = self._clients.setdefault(client, _Client())
            state.request = request
            state.version += 1
            state.submitted = time.monotonic()
            self._wake.notify_all()

    def forget(self, client: Hashable) -> None:
        """The client left: drop its request; a render in flight for it is not delivered."""
        with self._wake:
            self._clients.pop(client, None)

    def close(self, timeout: float = 30.0) -> None:
        """Stop the thread (after the render in flight, if any) and wait for it."""
        with self._wake:
            self._stopping = True
            self._wake.notify_all()
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _next_job(self) -> tuple[tuple[Hashable, int, ViewRequest, str] | None, float | None]:
        """The next (client, version, request, stage), or None and how long to wait before asking again."""
        wait = None
        for client, state in self._clients.items():
            if state.request is not None and state.done_version != state.version:
                return (client, state.version, state.request, "preview"), None
        now = time.monotonic()
        for client, state in self._clients.items():
            if state.request is None or state.done_stage == "full":
                continue
            rested = now - state.submitted
            if rested >= self.rest_s:
                return (client, state.version, state.request, "full"), None
            wait = self.rest_s - rested if wait is None else min(wait, self.rest_s - rested)
        return None, wait

    def _loop(self) -> None:
        while True:
            with self._wake:
                while True:
                    if self._stopping:
                        return
                    job, wait = self._next_job()
                    if job is not None:
                        break
                    self._wake.wait(wait)
            client, version, request, stage = job
            view = self._render(request, stage)
            with self._wake:
                state = self._clients.get(client)
                if state is None or state.version != version:
                    continue  # the client moved on (or left) while this rendered: stale
                full = stage == "full" or view.stride == request.stride or view.error is not None
                state.done_version, state.done_stage = version, "full" if full else "preview"
            try:
                self.deliver(client, request, view)
            except Exception as exc:  # a client that vanished mid-delivery must not stop the others' renders
                print(f"viewer: could not deliver a frame to client {client}: {exc}", file=sys.stderr)

    def _render(self, request: ViewRequest, stage: str) -> RenderedView:
        stride = request.preview_stride if stage == "preview" else request.stride
        began = time.perf_counter()
        try:
            camera = self.renderer.camera(request, math.lcm(request.stride, request.preview_stride))
            return self.renderer.render(request.scene, camera, request.source_views, stride, stage)
        except Exception as exc:  # the server keeps serving; the client sees the reason
            message = f"{type(exc).__name__}: {exc}".splitlines()[0]
            print(f"viewer: render failed ({message})", file=sys.stderr)
            return RenderedView(stage=stage, stride=stride, layers={}, sources=(),
                                seconds=time.perf_counter() - began, error=message)
