"""The viewer's renderer: a frame at a training pose equals ``predict``; progressive, cancellable, per-client
rendering; cameras no source sees render something finite."""

import dataclasses
import re
import threading
import time

import numpy as np
import pytest
import torch

from gpnerf_core.errors import DataError
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.tools.viewer.renderer import ProgressiveRenderer, SceneRenderer, ViewRequest, highlight_class
from gpnerf_core.tools.viewer.server import ViewerOptions, ViewerServer


def test_a_camera_at_a_frame_is_that_frame_rendered_as_evaluation_does_and_compared_with_it(tiny, at_frame):
    from gpnerf_core.evaluation import metrics as M

    components, renderer = tiny
    scene = renderer.frames.scene("layout_00")
    index = scene.train_frames[1]
    frame = renderer.frames.frame(scene, index)
    request = at_frame(renderer, "layout_00", index)
    camera = renderer.camera(request, multiple=8)
    frame_camera = renderer.frames.camera(scene, frame)
    assert torch.allclose(camera.c2w, frame_camera.c2w, atol=1e-6)
    assert torch.allclose(camera.intrinsics, frame_camera.intrinsics, atol=1e-5)
    view = renderer.render("layout_00", camera, 2, 2, "full")
    # the frame's own camera, with sources among the other training frames (never the frame itself)
    candidates = [i for i in scene.train_frames if i != index]
    positions = components.view_selector.select(frame_camera.c2w, scene.c2w[candidates], 2, None)
    sources = renderer.frames.source_views(scene, [candidates[p] for p in positions])
    assert view.frame == index and view.sources == tuple(candidates[p] for p in positions)
    exact = components.model.predict(frame_camera, sources, stride=2, chunk_rays=256)
    for name in ("rgb", "depth", "semantic", "logits"):
        assert torch.equal(getattr(view.prediction, name), getattr(exact, name)), name
    assert set(view.layers) == {"rgb", "depth", "semantic", "features", "error"}
    assert view.layers["rgb"].shape == (16, 24, 3) and view.layers["error"].shape == (16, 24, 3)
    real = torch.nn.functional.avg_pool2d(frame.rgb.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    assert view.psnr == pytest.approx(M.psnr(exact.rgb.clamp(0, 1), real), abs=1e-3)


def test_a_camera_between_frames_is_the_engine_s_render_for_that_camera(tiny, at_frame):
    components, renderer = tiny
    scene = renderer.frames.scene("layout_00")
    request = at_frame(renderer, "layout_00", scene.train_frames[1])
    request = dataclasses.replace(request, position=tuple(p + 0.05 for p in request.position))
    camera = renderer.camera(request, multiple=8)
    view = renderer.render("layout_00", camera, 2, 2, "full")
    candidates = list(scene.train_frames)
    positions = components.view_selector.select(camera.c2w, scene.c2w[candidates], 2, None)
    sources = renderer.frames.source_views(scene, [candidates[p] for p in positions])
    assert view.frame is None and view.psnr is None and "error" not in view.layers
    exact = components.model.predict(camera, sources, stride=2, chunk_rays=256)
    for name in ("rgb", "depth", "semantic", "logits"):  # the very same computation for the converted camera
        assert torch.equal(getattr(view.prediction, name), getattr(exact, name)), name
    assert view.layers["semantic"].shape == (32, 48, 3)


def test_feature_cache_gives_the_same_frame(tiny, at_frame):
    components, renderer = tiny
    cached = SceneRenderer(components.model, renderer.frames, components.view_selector, num_classes=9,
                           chunk_rays=256, default_source_views=2, feature_cache=SourceFeatureCache(16))
    request = at_frame(renderer, "layout_00", 0)
    plain = renderer.render("layout_00", renderer.camera(request, 8), 2, 4, "full")
    for _ in range(2):  # the second render takes every source from the cache
        again = cached.render("layout_00", cached.camera(request, 8), 2, 4, "full")
        assert torch.allclose(again.prediction.rgb, plain.prediction.rgb, atol=1e-5)
    assert cached.feature_cache.stats.hits == 2


class Collector:
    def __init__(self):
        self.got = []
        self.arrived = threading.Condition()

    def __call__(self, client, request, view):
        with self.arrived:
            self.got.append((client, request, view))
            self.arrived.notify_all()

    def wait_for(self, count, timeout=60.0):
        end = time.monotonic() + timeout
        with self.arrived:
            while len(self.got) < count:
                assert self.arrived.wait(max(0.0, end - time.monotonic())), f"only {len(self.got)} frames arrived"
        return list(self.got)


def test_preview_then_full_frame_per_client(tiny, at_frame):
    _, renderer = tiny
    collector = Collector()
    before = set(threading.enumerate())
    progressive = ProgressiveRenderer(renderer, collector, rest_s=0.05)
    try:
        a = at_frame(renderer, "layout_00", 0, preview_stride=8, stride=2)
        b = at_frame(renderer, "unseen_00", 2, preview_stride=4, stride=4)  # preview is already the full stride
        progressive.submit("a", a)
        progressive.submit("b", b)
        got = collector.wait_for(3)
        time.sleep(0.3)
        got = collector.got
        stages = {client: [(v.stage, v.stride) for c, _, v in got if c == client] for client in ("a", "b")}
        assert stages == {"a": [("preview", 8), ("full", 2)], "b": [("preview", 4)]}
        for client, request, view in got:  # every frame went to the client that asked, for its own request
            assert request == {"a": a, "b": b}[client] and view.error is None
    finally:
        progressive.close()
    assert not progressive.alive and set(threading.enumerate()) == before


def test_stale_requests_are_dropped_and_a_departed_client_gets_nothing(tiny, at_frame):
    _, renderer = tiny
    collector = Collector()
    progressive = ProgressiveRenderer(renderer, collector, rest_s=0.05)
    try:
        requests = [at_frame(renderer, "layout_00", i % 4, stride=2, preview_stride=8) for i in range(6)]
        for request in requests:  # a moving camera: only the newest pose may be delivered at the end
            progressive.submit("moving", request)
        progressive.submit("leaving", requests[0])
        progressive.forget("leaving")
        got = collector.wait_for(2)
        time.sleep(0.3)
        got = collector.got
        assert all(client == "moving" for client, _, _ in got)
        assert got[-1][1] == requests[-1] and got[-1][2].stage == "full"
        assert [v.stage for _, r, v in got if r == requests[-1]] == ["preview", "full"]
        assert len(got) <= 3  # at most one stale preview, started before the newest camera arrived
    finally:
        progressive.close()


def test_cameras_no_source_sees_render_finite_frames_and_errors_keep_serving(tiny, at_frame):
    _, renderer = tiny
    scene = renderer.frames.scene("layout_00")
    collector = Collector()
    progressive = ProgressiveRenderer(renderer, collector, rest_s=0.0)
    try:
        base = at_frame(renderer, "layout_00", 0, stride=4, preview_stride=4)
        centres = scene.c2w[:, :3, 3]
        far_behind = tuple((centres.mean(0) - 50 * scene.c2w[0, :3, 2]).tolist())  # behind every source camera
        inside = tuple((centres[0] + scene.c2w[0, :3, 2] * 2.0).tolist())  # among the depth points
        unknown = ViewRequest(**{**base.__dict__, "scene": "no_such_scene"})
        for position in (far_behind, inside):
            progressive.submit(position, ViewRequest(**{**base.__dict__, "position": position}))
        progressive.submit("unknown", unknown)
        got = collector.wait_for(3)
        views = {client: view for client, _, view in got}
        for position in (far_behind, inside):
            view = views[position]
            assert view.error is None
            assert np.isfinite(view.layers["rgb"]).all() and torch.isfinite(view.prediction.rgb).all()
            assert torch.isfinite(view.prediction.depth).all() and torch.isfinite(view.prediction.logits).all()
        assert "no_such_scene" in views["unknown"].error and views["unknown"].layers == {}
        progressive.submit("after", base)  # still serving
        assert collector.wait_for(4)[-1][2].error is None
    finally:
        progressive.close()


class _WithoutFrames:
    """The tiny dataset with one scene's frame lists emptied (as a capture folder with no usable frame)."""

    def __init__(self, dataset, empty):
        self.dataset, self.empty = dataset, empty

    def load_scene(self, name):
        scene = self.dataset.load_scene(name)
        return dataclasses.replace(scene, train_frames=(), eval_frames=()) if name == self.empty else scene

    def __getattr__(self, name):
        return getattr(self.dataset, name)


def test_a_scene_with_no_frames_is_one_line_and_the_thread_keeps_serving(tiny, at_frame):
    components, renderer = tiny
    frames = FrameCache(_WithoutFrames(components.dataset, "unseen_00"), torch.device("cpu"))
    empty = SceneRenderer(components.model, frames, components.view_selector, num_classes=9, chunk_rays=256,
                          default_source_views=2)
    options = ViewerOptions(host="127.0.0.1", port=0, scene="unseen_00", scenes=("unseen_00", "layout_00"),
                            stride=2, preview_stride=8, source_views=2)
    before = set(threading.enumerate())
    with pytest.raises(DataError, match="scene 'unseen_00' has no training frames"):
        ViewerServer(empty, options).start()
    assert set(threading.enumerate()) == before
    collector = Collector()
    progressive = ProgressiveRenderer(empty, collector, rest_s=0.0)
    try:
        good = at_frame(renderer, "layout_00", 0, stride=4, preview_stride=4)
        progressive.submit("client", ViewRequest(**{**good.__dict__, "scene": "unseen_00"}))
        assert "has no training frames" in collector.wait_for(1)[0][2].error
        progressive.submit("client", good)
        assert collector.wait_for(2)[1][2].error is None
    finally:
        progressive.close()


def test_highlighting_a_class_dims_every_other_pixel():
    picture = np.full((2, 3, 3), 200, dtype=np.uint8)
    labels = np.array([[0, 1, 2], [1, 1, 0]])
    out = highlight_class(picture, labels, 1)
    assert (out[labels == 1] == 200).all() and (out[labels != 1] == 50).all() and (picture == 200).all()


def test_the_preview_samples_around_the_swept_depth_and_the_full_frame_as_configured(tiny, at_frame):
    from gpnerf_core.errors import ConfigError
    from gpnerf_core.tools.viewer.renderer import preview_of
    from omegaconf import OmegaConf

    components, renderer = tiny
    model = components.model
    preview = preview_of(OmegaConf.create({"preview_samples": 3, "preview_depth_source": "cost_volume"}))
    fast = SceneRenderer(model, renderer.frames, components.view_selector, num_classes=9, chunk_rays=256,
                         default_source_views=2, preview=preview)
    request = at_frame(renderer, "layout_00", 0)
    camera = fast.camera(request, 8)
    configured = (model.sampling, model.depth_source, model.fine_samples)
    swept = fast.render("layout_00", camera, 2, 8, "preview").prediction
    as_full = renderer.render("layout_00", camera, 2, 8, "preview").prediction
    assert (model.sampling, model.depth_source, model.fine_samples) == configured  # restored after the preview
    assert swept.rgb.shape == as_full.rgb.shape and not torch.equal(swept.rgb, as_full.rgb)
    full = fast.render("layout_00", camera, 2, 4, "full").prediction
    assert torch.equal(full.rgb, renderer.render("layout_00", camera, 2, 4, "full").prediction.rgb)
    try:  # a failure inside the preview leaves the configured sampling in place
        with model.preview_sampling(*preview):
            raise RuntimeError("render failed")
    except RuntimeError:
        pass
    assert (model.sampling, model.depth_source, model.fine_samples) == configured
    assert preview_of(OmegaConf.create({"preview_samples": 0, "preview_depth_source": "cost_volume"})) is None
    for values, message in (({"preview_samples": -1, "preview_depth_source": "cost_volume"},
                              "view.preview_samples=-1: expected an integer >= 0"),
                             ({"preview_samples": 4, "preview_depth_source": "sweep"},
                              "view.preview_depth_source='sweep'; expected one of: cost_volume, source_depth")):
        with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
            preview_of(OmegaConf.create(values))
