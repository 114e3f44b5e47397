"""The viewer's server: starts on a free localhost port, serves the page, renders the camera a websocket client sends
(the same frame ``predict`` gives), refuses a port in use, and stops with no thread left."""

import socket
import threading
import time
import urllib.request

import msgspec
import pytest
import torch
import viser
from viser import _messages
from websockets.sync.client import connect

from gpnerf_core.errors import ConfigError
from gpnerf_core.tools.viewer.query import Query
from gpnerf_core.tools.viewer.server import ViewerOptions, ViewerServer, check_port_free, depth_points

OPTIONS = dict(host="127.0.0.1", port=0, scene="layout_00", scenes=("unseen_00", "layout_00"), stride=2,
               preview_stride=8, source_views=2, class_names=("floor", "wall"))


def _camera_message(request, height=320, width=480):
    message = _messages.ViewerCameraMessage(
        wxyz=request.wxyz, position=request.position, fov=request.fov, near=0.01, far=100.0, image_height=height,
        image_width=width, look_at=tuple(float(p) for p in request.position), up_direction=(0.0, -1.0, 0.0),
    )
    return msgspec.msgpack.encode(message.as_serializable_dict())


def _wait(condition, timeout=60.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def test_serves_a_client_its_camera_and_stops_cleanly(tiny, at_frame):
    components, renderer = tiny
    before = set(threading.enumerate())
    server = ViewerServer(renderer, ViewerOptions(**OPTIONS)).start()
    try:
        assert server.url.startswith("http://127.0.0.1:") and server.port > 0
        page = urllib.request.urlopen(server.url, timeout=10).read().decode()
        assert "<html" in page.lower()
        request = at_frame(renderer, "layout_00", 0)
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=[f"viser-v{viser.__version__}"],
                     open_timeout=10, close_timeout=5, max_size=None) as websocket:
            websocket.send(_camera_message(request))
            _wait(lambda: server.frames_delivered >= 2)  # the preview, then the full frame
            (state,) = server._clients.values()
            view = state.last
            assert view.stage == "full" and view.stride == 2 and view.error is None
            scene = renderer.frames.scene("layout_00")
            assert view.frame == 0 and 0 not in view.sources  # at a frame: its own camera, compared with it
            camera = renderer.frames.camera(scene, renderer.frames.frame(scene, 0))
            sources = renderer.frames.source_views(scene, list(view.sources))
            expected = components.model.predict(camera, sources, stride=2, chunk_rays=256)
            assert torch.equal(view.prediction.rgb, expected.rgb)
            assert torch.equal(view.prediction.logits, expected.logits)
            assert camera.width == 48  # the browser's 3:2 canvas at the scene's 32 rows
            assert state.gui["layer"].options == ("rgb", "depth", "semantic", "features", "error")
            assert len(state.highlighted) == len(view.sources)
            state.layer = "semantic"  # as the Layer dropdown sets it; then a class is highlighted
            state.gui["highlight"].value = "wall"
            server._show(next(iter(server.server.get_clients().values())), state, state.last_request, view)
            assert state.gui["legend"].visible and state.gui["highlight"].visible
    finally:
        server.stop()
    _wait(lambda: set(threading.enumerate()) <= before, timeout=15)


def test_a_port_in_use_is_refused_naming_it(tiny):
    _, renderer = tiny
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f"view.port={port}: 127.0.0.1:{port} is already in use"):
            check_port_free("127.0.0.1", port)
        before = set(threading.enumerate())
        with pytest.raises(ConfigError, match="already in use"):
            ViewerServer(renderer, ViewerOptions(**{**OPTIONS, "port": port})).start()
        assert set(threading.enumerate()) == before


def test_a_scene_that_cannot_be_shown_is_refused_before_serving(tiny):
    _, renderer = tiny
    before = set(threading.enumerate())
    with pytest.raises(Exception, match="no_such_scene"):
        ViewerServer(renderer, ViewerOptions(**{**OPTIONS, "scene": "no_such_scene"})).start()
    assert set(threading.enumerate()) == before


def test_depth_points_lie_on_the_frames_depths(tiny):
    _, renderer = tiny
    scene = renderer.frames.scene("layout_00")
    frame = renderer.frames.frame(scene, 0)
    points, colours = depth_points([frame], 200)
    assert 0 < len(points) <= 200 and colours.shape == points.shape
    w2c = torch.linalg.inv(frame.c2w.double())
    camera = (w2c[:3, :3] @ torch.from_numpy(points).double().T + w2c[:3, 3:4]).T
    uv = (frame.intrinsics.double() @ camera.T).T
    u, v = (uv[:, 0] / uv[:, 2]).round().long(), (uv[:, 1] / uv[:, 2]).round().long()
    assert torch.allclose(camera[:, 2].float(), frame.depth[v, u], atol=1e-4)


MVSPLAT = ["+experiment=baselines/mvsplat", "model.feature_dim=8", "model.transformer_layers=1",
           "model.depth_candidates=4", "model.cost_unet_dim=4", "model.depth_unet_dim=4", "model.unet_levels=2",
           "model.sh_degree=1", "model.feature_extractor.widths=[8,8,8,16]", "threads=1"]


def test_a_gaussian_family_shows_its_gaussians_as_splats_in_either_colouring(tiny, at_frame):
    from gpnerf_core.config.compose import compose
    from gpnerf_core.model.build import build_components
    from gpnerf_core.model.feature_cache import SourceFeatureCache
    from gpnerf_core.tools.viewer.renderer import SceneRenderer
    from pipeline_check import TINY_SCENES

    components = build_components(compose([*MVSPLAT, *TINY_SCENES]))
    model = components.model.eval()
    renderer = SceneRenderer(model, tiny[1].frames, components.view_selector,
                             num_classes=components.classes.num_classes, chunk_rays=256, default_source_views=2,
                             feature_cache=SourceFeatureCache(64))
    assert renderer.draws_gaussians and not tiny[1].draws_gaussians
    server = ViewerServer(renderer, ViewerOptions(**OPTIONS)).start()
    try:
        request = at_frame(renderer, "layout_00", 0)
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=[f"viser-v{viser.__version__}"],
                     open_timeout=10, close_timeout=5, max_size=None) as websocket:
            websocket.send(_camera_message(request))
            _wait(lambda: server.frames_delivered >= 2)
            (state,) = server._clients.values()
            assert state.splats is not None and state.splats_shown[:3] == ("layout_00", state.last.sources, "rgb")
            first = state.splats
            misses = renderer.feature_cache.stats.misses  # the splats reuse the rendered view's Gaussians
            state.gui["splat_colours"].value = "class"
            server._show_splats(next(iter(server.server.get_clients().values())), state, "layout_00",
                                state.last.sources)
            assert state.splats is not first and state.splats_shown[2] == "class"
            assert renderer.feature_cache.stats.misses == misses
            # coloured by a query's relevancy (here the first Gaussian's own feature): sent again, in other colours
            gaussians = renderer.gaussians("layout_00", state.last.sources)
            state.query = Query(gaussians.features[0], "Gaussian 0")
            coloured = state.splats
            state.gui["splat_colours"].value = "relevancy"
            server._show_splats(next(iter(server.server.get_clients().values())), state, "layout_00",
                                state.last.sources)
            assert state.splats is not coloured and state.splats_shown[3] is state.query
            assert "not coloured" not in state.gui["query_status"].content
            state.query = Query(torch.ones(gaussians.features.shape[1] + 1), "text 'x'")  # another dimension
            server._show_splats(next(iter(server.server.get_clients().values())), state, "layout_00",
                                state.last.sources)
            assert state.gui["query_status"].content.startswith("**Gaussians not coloured by relevancy**: the query "
                                                                "embedding has")
            state.gui["query_click"].value = True  # clicks and shift-dragged boxes reach the query, then no more
            client = next(iter(server.server.get_clients().values()))
            assert {entry.event_type for entry in client.scene._scene_pointer_cb} == {"click", "rect-select"}
            state.gui["query_click"].value = False
            assert not client.scene._scene_pointer_cb
            state.gui["gaussians"].value = False
            server._show_splats(next(iter(server.server.get_clients().values())), state, "layout_00",
                                state.last.sources)
            assert state.splats.visible is False
    finally:
        server.stop()


def test_splat_arrays_hold_the_gaussians_covariances_and_label_colours():
    from gpnerf_core.geometry.gaussians.scene import GaussianScene
    from gpnerf_core.tools.viewer.splats import splat_arrays

    scene = GaussianScene(means=torch.zeros(2, 3), scales=torch.tensor([[1.0, 2.0, 3.0], [0.1, 0.1, 0.1]]),
                          rotations=torch.tensor([[1.0, 0, 0, 0], [0, 0, 0, 1.0]]), opacities=torch.tensor([0.5, 1.0]),
                          harmonics=torch.zeros(2, 3, 1), labels=torch.tensor([1, -1]))
    arrays = splat_arrays(scene, "class", 3)
    assert arrays["covariances"][0].diagonal().tolist() == pytest.approx([1.0, 4.0, 9.0])
    assert arrays["rgbs"][1].tolist() == pytest.approx([0.5, 0.5, 0.5])  # unlabelled: its own colour (C0 * 0 + 0.5)
    assert arrays["rgbs"][0].tolist() != pytest.approx([0.5, 0.5, 0.5]) and arrays["opacities"].shape == (2, 1)
