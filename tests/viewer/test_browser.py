"""A real browser: headless Chromium opens the viewer, the first rendered frame arrives, and the screenshot shows the
scene (the rendered view as the background, frustums and controls), not a blank or an error page; a click on the view
then queries by example. The screenshot is
docs/images/viewer.png when GPNERF_VIEWER_SCREENSHOT names that path; GPNERF_VIEWER_CHECKPOINT=<.pt> shows that trained
model instead of the tests' tiny untrained one (what the docs' screenshot shows)."""

import base64
import io
import itertools
import json
import os
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from websockets.sync.client import connect

from gpnerf_core.tools.viewer.server import ViewerOptions, ViewerServer

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="headless Chromium is not installed (Debian: apt-get install -y chromium; .ci/run does)"
)


class DevTools:
    """The Chrome DevTools Protocol of one page, over its websocket (localhost only)."""

    def __init__(self, url: str) -> None:
        self.socket = connect(url, max_size=None, open_timeout=20)
        self.ids = itertools.count(1)

    def call(self, method: str, timeout: float = 30.0, **params):
        ident = next(self.ids)
        self.socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            reply = json.loads(self.socket.recv(timeout=max(0.1, end - time.monotonic())))
            if reply.get("id") == ident:
                assert "error" not in reply, reply
                return reply["result"]

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")


def _wait(condition, timeout, what):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.1)


def _browser(tmp_path):
    profile = tmp_path / "profile"
    process = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", "--window-size=1280,800", "--remote-debugging-address=127.0.0.1",
         "--remote-debugging-port=0", f"--user-data-dir={profile}", "--no-first-run", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    port_file = profile / "DevToolsActivePort"
    _wait(lambda: port_file.exists() and port_file.read_text().strip(), 60, "Chromium's DevTools port")
    port = int(port_file.read_text().split()[0])
    pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
    page = next(p for p in pages if p["type"] == "page")
    return process, DevTools(page["webSocketDebuggerUrl"])


def trained_renderer(checkpoint: str):
    """The renderer of a trained checkpoint (``GPNERF_VIEWER_CHECKPOINT``: the docs' screenshot shows a trained model),
    its class names and the source-view count it was trained with."""
    import torch

    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.engine.opening import open_trained
    from gpnerf_core.model.trained import load_trained
    from gpnerf_core.tools.viewer.renderer import SceneRenderer

    opened = open_trained(load_trained(checkpoint), command="view", weights="trained", device=torch.device("cpu"))
    cfg, components = opened.cfg, opened.components
    renderer = SceneRenderer(components.model.eval(), FrameCache(components.dataset, torch.device("cpu")),
                             components.view_selector, num_classes=components.classes.num_classes,
                             chunk_rays=int(cfg.eval.chunk_rays), default_source_views=int(cfg.model.num_source_views))
    return renderer, tuple(components.classes.names), int(cfg.model.num_source_views)


def test_chromium_shows_the_rendered_scene(tiny, tmp_path):
    _, renderer = tiny
    class_names, source_views = ("floor", "wall", "table"), 2
    if os.environ.get("GPNERF_VIEWER_CHECKPOINT"):
        renderer, class_names, source_views = trained_renderer(os.environ["GPNERF_VIEWER_CHECKPOINT"])
    options = ViewerOptions(host="127.0.0.1", port=0, scene="layout_00", scenes=("unseen_00", "layout_00"),
                            stride=2, preview_stride=8, source_views=source_views, class_names=class_names)
    server = ViewerServer(renderer, options).start()
    process = devtools = None
    try:
        process, devtools = _browser(tmp_path)
        devtools.call("Page.enable")
        devtools.call("Emulation.setDeviceMetricsOverride", width=1280, height=800, deviceScaleFactor=1, mobile=False)
        devtools.call("Page.navigate", url=server.url)
        _wait(lambda: server.frames_delivered >= 2, 90, "the preview and the full frame")
        _wait(lambda: devtools.evaluate("document.querySelectorAll('canvas').length") or 0, 30, "the 3D canvas")
        time.sleep(2.0)  # let the browser decode and draw the last frame
        text = devtools.evaluate("document.body.innerText") or ""
        assert "Render stride" in text and "full" in text, text[:500]  # the controls and the frame's status
        # the page opens at the first training frame's own camera, compared with it, that frame's frustum hidden
        first = renderer.frames.scene("layout_00").train_frames[0]
        assert f"at frame {first}: PSNR" in text, text[:500]
        (state,) = server._clients.values()
        assert state.hidden_frustums == {first} and not state.frustums[first].visible
        assert all(handle.visible for index, handle in enumerate(state.frustums) if index != first)
        shot = devtools.call("Page.captureScreenshot", format="png")["data"]
        # a click on the view queries by example (after the screenshot, which shows the view without a query)
        state.gui["query_click"].value = True
        time.sleep(0.5)  # the click callback reaches the page
        for kind in ("mousePressed", "mouseReleased"):
            devtools.call("Input.dispatchMouseEvent", type=kind, x=640, y=400, button="left", clickCount=1)
        _wait(lambda: state.query is not None, 30, "the click's query")
        assert state.gui["query_status"].content.startswith("**query** pixel ("), state.gui["query_status"].content
    finally:
        if devtools is not None:
            devtools.socket.close()
        if process is not None:
            process.terminate()
            process.wait(timeout=30)
        server.stop()
    png = base64.b64decode(shot)
    picture = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    assert picture.shape[:2] == (800, 1280)
    # not blank: many colours and real contrast (an empty or error page is a few flat colours)
    assert len(np.unique(picture.reshape(-1, 3), axis=0)) > 500 and picture.std() > 20
    # the rendered frame fills the background: its centre is not the page's flat background colour
    centre = picture[300:500, 300:700].reshape(-1, 3)
    assert len(np.unique(centre, axis=0)) > 100
    target = os.environ.get("GPNERF_VIEWER_SCREENSHOT")
    if target:
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        Path(target).write_bytes(png)
