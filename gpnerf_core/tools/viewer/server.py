"""The viser server of the viewer: per browser, the chosen scene's cameras (frustums with thumbnails; training frames
blue, held-out frames orange), the depth points of its training frames, the model's novel view for the browser's
camera as the background (a layer at a time), the source views of that view highlighted (yellow), the time per frame,
and controls for scene, layer, number of source views and render strides; for a Gaussian family, its 3D Gaussians
themselves as splats (those of the view's sources), in their own colours or their classes'.

Every browser (client) has its own controls, scene content, camera and frames: nothing one client does reaches
another's view."""

from __future__ import annotations

import errno
import socket
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation import visualize as vis
from gpnerf_core.types import Scene
from gpnerf_core.tools.viewer.camera import vertical_fov, viser_pose
from gpnerf_core.tools.viewer.query import Query, answer, box_query, click_query
from gpnerf_core.tools.viewer.splats import splat_arrays
from gpnerf_core.tools.viewer.renderer import (
    LAYERS,
    ProgressiveRenderer,
    RenderedView,
    SceneRenderer,
    ViewRequest,
    highlight_class,
)

TRAIN_COLOUR = (40, 110, 220)
"""Frustums of training frames (candidate source views)."""
HELD_OUT_COLOUR = (240, 140, 30)
"""Frustums of held-out frames (never source views)."""
SOURCE_COLOUR = (250, 220, 0)
"""Frustums of the source views of the view on screen."""
FRUSTUM_LINES = {"thickness": 2.0, "thickness_units": "screen"}
"""Frustum edges in pixels: in world units a neighbour's edges seen from a training camera fill the view as planks."""
STRIDES = ("1", "2", "4", "8", "16")


@dataclass(frozen=True)
class ViewerOptions:
    """Settings of a viewer (``view.*`` of the config).

    Attributes:
        host, port: where the server listens (port 0: any free port).
        scene: the scene shown first; scenes: the scenes a client may choose.
        stride, preview_stride: pixels per rendered cell of the full frame and of the preview.
        source_views: source views per render (0 = the model's ``num_source_views``).
        class_names: the head's classes, for the legend (empty: no legend).
        max_points: depth points shown per scene; thumbnail_height: pixels of a frustum's thumbnail.
        text_encoder: ``text -> [C]`` query embedding (the feature provider's text encoder,
            ``features.queries.text_embedding``), or None: no text box.
    """

    host: str
    port: int
    scene: str
    scenes: tuple[str, ...]
    stride: int
    preview_stride: int
    source_views: int
    class_names: tuple[str, ...] = ()
    max_points: int = 20000
    thumbnail_height: int = 48
    text_encoder: Callable[[str], torch.Tensor] | None = None


def check_port_free(host: str, port: int) -> None:
    """Refuse a port another program listens on (viser would silently move to the next one)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ConfigError(
                    f"view.port={port}: {host}:{port} is already in use; choose another view.port"
                ) from None
            raise ConfigError(
                f"view.host={host!r}, view.port={port}: cannot listen there ({exc.strerror or exc})"
            ) from None


def depth_points(frames: Sequence[Any], max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of the known depths of ``frames`` (``Frame``s), about ``max_points`` in all.

    Returns:
        ``([N, 3] float32 metres, [N, 3] uint8)``; empty when no frame has depth.
    """
    if not frames:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    per_frame = max(1, max_points // len(frames))
    points, colours = [], []
    for frame in frames:
        depth = frame.depth.numpy()
        v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
        if len(v) == 0:
            continue
        keep = np.linspace(0, len(v) - 1, min(per_frame, len(v))).round().astype(np.int64)
        v, u = v[keep], u[keep]
        z = depth[v, u].astype(np.float64)
        inverse = np.linalg.inv(frame.intrinsics.double().numpy())
        camera = (inverse @ np.stack([u, v, np.ones_like(z)])) * z  # pixel centres at integers
        c2w = frame.c2w.double().numpy()
        points.append((c2w[:3, :3] @ camera + c2w[:3, 3:4]).T.astype(np.float32))
        colours.append((frame.rgb.numpy()[v, u] * 255).round().clip(0, 255).astype(np.uint8))
    if not points:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    return np.concatenate(points), np.concatenate(colours)


def _thumbnail(rgb: torch.Tensor, height: int) -> np.ndarray:
    step = max(1, int(rgb.shape[0]) // height)
    return (rgb[::step, ::step].clamp(0, 1).numpy() * 255).round().astype(np.uint8)


@dataclass
class _ClientState:
    """What one browser sees and chose."""

    scene: str
    layer: str = "rgb"
    source_views: int = 0
    stride: int = 2
    preview_stride: int = 8
    last: RenderedView | None = None
    last_request: ViewRequest | None = None
    highlighted: list[Any] = field(default_factory=list)
    splats: Any = None
    splats_shown: tuple[Any, ...] | None = None
    """The splat node and what it shows: (scene, sources, colours, query, threshold), so the same Gaussians are not
    sent twice."""
    frustums: list[Any] = field(default_factory=list)
    hidden_frustums: set[int] = field(default_factory=set)
    query: Query | None = None
    """The query every view shown carries (a click's or a text's), or None."""
    query_seconds: float | None = None
    """Seconds the last query answer took (similarity and picture, no render)."""
    gui: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


class ViewerServer:
    """The viewer's web server; ``start`` it, read ``url``, ``stop`` it (idempotent; joins its threads).

    Args:
        renderer: renders views of the dataset's scenes.
        options: host, port, scenes, strides and the legend's class names.
    """

    def __init__(self, renderer: SceneRenderer, options: ViewerOptions) -> None:
        self.renderer = renderer
        self.options = options
        self.server: Any = None
        self.progressive: ProgressiveRenderer | None = None
        self._clients: dict[int, _ClientState] = {}
        self._clients_lock = threading.Lock()
        self.frames_delivered = 0

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        host = f"[{self.options.host}]" if ":" in self.options.host else self.options.host
        return f"http://{host}:{self.port}"

    def start(self) -> "ViewerServer":
        """Listen on ``options.host:options.port``; a port in use is a ``ConfigError`` naming it."""
        import viser

        options = self.options
        check_port_free(options.host, options.port)
        self.renderer.frames.scene(options.scene)  # a scene that cannot be shown is refused before serving
        self.server = viser.ViserServer(host=options.host, port=options.port, verbose=False)
        if options.port and self.port != options.port:  # taken between the check and the bind: viser moved on
            self.server.stop()
            raise ConfigError(f"view.port={options.port}: {options.host}:{options.port} is already in use; "
                              "choose another view.port")
        self.progressive = ProgressiveRenderer(self.renderer, self._deliver)
        self._set_initial_camera(options.scene)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        return self

    def stop(self) -> None:
        if self.progressive is not None:
            self.progressive.close()
            self.progressive = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self) -> "ViewerServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- clients ------------------------------------------------------------------------------------------------

    def _set_initial_camera(self, scene_name: str) -> None:
        """At the first training frame's own camera (as nerfstudio opens at a training camera): the page opens on that
        frame rendered by the model, compared with it, its frustum hidden while the camera sits in it."""
        scene = self.renderer.frames.scene(scene_name)
        index = scene.train_frames[0]
        c2w = scene.c2w[index].double().numpy()
        camera = self.server.initial_camera
        camera.position = tuple(c2w[:3, 3])
        camera.look_at = tuple(c2w[:3, 3] + c2w[:3, 2] * (scene.near + scene.far) / 2)
        camera.up = tuple(-c2w[:3, 1])
        camera.fov = vertical_fov(scene.intrinsics[index], scene.height)

    def _connect(self, client: Any) -> None:
        options = self.options
        state = _ClientState(scene=options.scene, source_views=options.source_views, stride=options.stride,
                             preview_stride=options.preview_stride)
        with self._clients_lock:
            self._clients[client.client_id] = state
        self._build_gui(client, state)
        self._show_scene(client, state)
        client.camera.on_update(lambda camera: self._camera_moved(client, state))
        self._camera_moved(client, state)  # viser connects a client once its first camera arrived: render that one

    def _disconnect(self, client: Any) -> None:
        with self._clients_lock:
            self._clients.pop(client.client_id, None)
        if self.progressive is not None:
            self.progressive.forget(client.client_id)

    def _build_gui(self, client: Any, state: _ClientState) -> None:
        gui = client.gui
        scene = self.renderer.frames.scene(state.scene)
        state.gui["scene"] = gui.add_dropdown("Scene", list(self.options.scenes), initial_value=state.scene)
        state.gui["layer"] = gui.add_dropdown("Layer", ["rgb"], initial_value="rgb")
        most = max(1, len(scene.train_frames))
        initial = min(state.source_views or self.renderer.default_source_views, most)
        state.gui["sources"] = gui.add_slider("Source views", min=1, max=most, step=1, initial_value=initial)
        stride_options = list(dict.fromkeys([*STRIDES, str(state.stride), str(state.preview_stride)]))
        state.gui["stride"] = gui.add_dropdown("Render stride", stride_options, initial_value=str(state.stride))
        state.gui["preview"] = gui.add_dropdown("Preview stride", stride_options,
                                                initial_value=str(state.preview_stride))
        state.gui["cameras"] = gui.add_checkbox("Cameras", True, hint="show the frames' frustums and thumbnails")
        if self.renderer.draws_gaussians:
            state.gui["gaussians"] = gui.add_checkbox("Gaussians", True,
                                                      hint="draw the model's 3D Gaussians (those of the view's sources)")
            colours = ["rgb", "class", "relevancy"] if self.options.class_names else ["rgb", "relevancy"]
            state.gui["splat_colours"] = gui.add_dropdown("Gaussian colours", colours, initial_value="rgb")
        state.gui["snap"] = gui.add_button("Snap to nearest frame")
        state.gui["status"] = gui.add_markdown("waiting for the first frame")
        self._build_query_gui(client, state)
        if self.options.class_names:
            state.gui["legend"] = gui.add_image(vis.class_legend(list(self.options.class_names)), label="Classes",
                                                format="png", visible=False)
            state.gui["highlight"] = gui.add_dropdown("Highlight class", ["none", *self.options.class_names],
                                                      initial_value="none", visible=False)

        def changed(_: Any) -> None:
            with state.lock:
                scene_changed = state.gui["scene"].value != state.scene
                state.scene = state.gui["scene"].value
                state.layer = state.gui["layer"].value
                state.source_views = int(state.gui["sources"].value)
                state.stride = int(state.gui["stride"].value)
                state.preview_stride = int(state.gui["preview"].value)
            if scene_changed:
                self._show_scene(client, state)
                self._move_camera_to(client, state, self.renderer.frames.scene(state.scene).train_frames[0])
            elif state.last is not None and state.last_request is not None:
                self._show(client, state, state.last_request, state.last)  # a layer switch needs no render
            self._camera_moved(client, state)

        for key in ("scene", "layer", "sources", "stride", "preview"):
            state.gui[key].on_update(changed)
        if "highlight" in state.gui:
            state.gui["highlight"].on_update(
                lambda _: state.last is not None and self._show(client, state, state.last_request, state.last)
            )
        state.gui["snap"].on_click(lambda _: self._snap(client, state))
        for key in ("gaussians", "splat_colours"):
            if key in state.gui:
                state.gui[key].on_update(
                    lambda _: state.last is not None and self._show_splats(client, state, state.last_request.scene,
                                                                          state.last.sources))

        def cameras_shown(_: Any) -> None:
            for index, handle in enumerate(state.frustums):
                handle.visible = bool(state.gui["cameras"].value) and index not in state.hidden_frustums

        state.gui["cameras"].on_update(cameras_shown)

    def _build_query_gui(self, client: Any, state: _ClientState) -> None:
        """Query controls: click to query by example, a text box (a provider with a text encoder), the relevancy
        threshold, clearing the query, and its status line."""
        gui = client.gui
        state.gui["query_click"] = gui.add_checkbox(
            "Query by click", False, hint="a click on the view (or a box dragged with shift held) makes its feature the "
                                          "query; every view then shows its relevancy (turbo) where it reaches the "
                                          "threshold")
        if self.options.text_encoder is not None:
            state.gui["query_text"] = gui.add_text("Query text", "", hint="a text embedded by the feature provider's "
                                                                          "text encoder")
        state.gui["threshold"] = gui.add_slider("Relevancy threshold", min=0.0, max=1.0, step=0.01, initial_value=0.5)
        state.gui["query_clear"] = gui.add_button("Clear query")
        state.gui["query_status"] = gui.add_markdown("no query")

        def clicked(event: Any) -> None:
            self.query_at(client, state, event.screen_pos)

        def boxed(event: Any) -> None:
            self.query_box(client, state, event.screen_min, event.screen_max)

        def click_mode(_: Any) -> None:
            if bool(state.gui["query_click"].value):
                client.scene.on_click()(clicked)
                client.scene.on_rect_select(modifier="shift")(boxed)
            else:
                client.scene.remove_click_callback(clicked)
                client.scene.remove_rect_select_callback(boxed)

        def text_changed(_: Any) -> None:
            text = str(state.gui["query_text"].value)
            if text.strip():
                self.query_text(client, state, text)

        def cleared(_: Any) -> None:
            state.query = None
            state.gui["query_status"].content = "no query"
            self._show_last(client, state)

        state.gui["query_click"].on_update(click_mode)
        state.gui["threshold"].on_update(lambda _: state.query is not None and self._show_last(client, state))
        # the splats follow the query too (``Gaussian colours``: relevancy): _show_last sends them again when it changed
        state.gui["query_clear"].on_click(cleared)
        if "query_text" in state.gui:
            state.gui["query_text"].on_update(text_changed)

    def query_at(self, client: Any, state: _ClientState, screen_pos: tuple[float, float]) -> None:
        """A click at ``screen_pos`` (0 to 1 from the top-left) on the view on screen becomes the query; the view is
        shown again with its relevancy (no render)."""
        view = state.last
        try:
            state.query = click_query(view.prediction if view is not None else None, screen_pos)
        except ConfigError as exc:
            state.gui["query_status"].content = f"**query refused**: {exc}"
            return
        self._show_last(client, state)

    def query_box(self, client: Any, state: _ClientState, screen_min: tuple[float, float],
                  screen_max: tuple[float, float]) -> None:
        """A box dragged on the view on screen (corners 0 to 1 from the top-left) becomes the query (the mean feature
        of its cells); the view is shown again with its relevancy (no render)."""
        view = state.last
        try:
            state.query = box_query(view.prediction if view is not None else None, screen_min, screen_max)
        except ConfigError as exc:
            state.gui["query_status"].content = f"**query refused**: {exc}"
            return
        self._show_last(client, state)

    def query_text(self, client: Any, state: _ClientState, text: str) -> None:
        """``text`` embedded by the provider's text encoder becomes the query; the view is shown again with it."""
        try:
            state.query = Query(embedding=self.options.text_encoder(text).detach().float().cpu(), label=repr(text))
        except (ConfigError, ValueError) as exc:
            state.gui["query_status"].content = f"**query refused**: {exc}"
            return
        self._show_last(client, state)

    def _show_last(self, client: Any, state: _ClientState) -> None:
        if state.last is not None and state.last_request is not None:
            self._show(client, state, state.last_request, state.last)

    def _with_query(self, state: _ClientState, view: RenderedView, picture: np.ndarray) -> np.ndarray:
        """``picture`` with the client's query's relevancy blended in (as it is without a query or when the query
        cannot be answered on this view, which the query status line then says)."""
        if state.query is None:
            return picture
        threshold = float(state.gui["threshold"].value)
        try:
            answered = answer(view.prediction, picture, state.query, threshold)
        except ConfigError as exc:
            state.gui["query_status"].content = f"**query refused**: {exc}"
            return picture
        state.query_seconds = answered.seconds
        state.gui["query_status"].content = (
            f"**query** {state.query.label}: {answered.selected:.0%} of the view at relevancy >= {threshold:.2f} "
            f"(peak {answered.peak:.2f}), {answered.seconds * 1000:.1f} ms")
        return answered.picture

    def _show_scene(self, client: Any, state: _ClientState) -> None:
        """Frustums with thumbnails and the depth points of the client's scene."""
        try:
            scene = self.renderer.frames.scene(state.scene)
        except Exception as exc:
            state.gui["status"].content = f"**cannot show scene {state.scene}**: {exc}"
            return
        client.scene.reset()
        state.splats, state.splats_shown = None, None
        held_out = set(scene.eval_frames)
        shown: list[Any] = []
        state.frustums, state.hidden_frustums = [], set()
        for index in range(scene.num_frames):
            frame = self.renderer.frames.frame(scene, index)
            wxyz, position = viser_pose(scene.c2w[index])
            state.frustums.append(client.scene.add_camera_frustum(
                f"/cameras/{index:04d}", fov=vertical_fov(scene.intrinsics[index], scene.height),
                aspect=scene.width / scene.height, scale=self._frustum_scale(scene),
                color=HELD_OUT_COLOUR if index in held_out else TRAIN_COLOUR, **FRUSTUM_LINES,
                image=_thumbnail(frame.rgb, self.options.thumbnail_height), format="jpeg", wxyz=wxyz,
                position=position, visible=bool(state.gui["cameras"].value),
            ))
            if index in scene.train_frames:
                shown.append(frame)
        points, colours = depth_points(shown, self.options.max_points)
        if len(points):
            client.scene.add_point_cloud("/depth_points", points=points, colors=colours,
                                         point_size=self._frustum_scale(scene) / 40)
        state.highlighted = []
        state.gui["sources"].max = max(1, len(scene.train_frames))

    @staticmethod
    def _frustum_scale(scene: Scene) -> float:
        """Frustum depth in metres: a quarter of the median distance from a camera to its nearest neighbour, within
        [0.02, 0.25] m (a ring of 36 cameras 0.26 m apart gets 0.065 m): neighbouring frustums do not overlap, and from
        a training camera (where the page opens) the neighbours' thumbnails stay small beside the rendered view."""
        centres = scene.c2w[:, :3, 3]
        if scene.num_frames < 2:
            return 0.1
        distances = torch.cdist(centres, centres)
        distances.fill_diagonal_(float("inf"))
        spacing = float(distances.min(dim=1).values.median())
        return max(0.02, min(0.25, spacing / 4 if spacing > 0 else 0.1))

    def _hide_frustum_at_lens(self, client: Any, state: _ClientState) -> None:
        """Hide the frustum the camera sits in (its thumbnail would cover the rendered view), show the others."""
        if not state.frustums or not bool(state.gui["cameras"].value):
            return
        try:
            scene = self.renderer.frames.scene(state.scene)
        except Exception:
            return
        position = torch.as_tensor(np.asarray(client.camera.position), dtype=torch.float32)
        near_lens = (scene.c2w[:, :3, 3] - position).norm(dim=-1) < self._frustum_scale(scene)
        hidden = {int(i) for i in torch.nonzero(near_lens).flatten()}
        for index in hidden ^ state.hidden_frustums:  # only the frustums whose visibility changes
            if index < len(state.frustums):
                state.frustums[index].visible = index not in hidden
        state.hidden_frustums = hidden

    def _move_camera_to(self, client: Any, state: _ClientState, index: int) -> None:
        scene = self.renderer.frames.scene(state.scene)
        c2w = scene.c2w[index].double().numpy()
        with client.atomic():
            client.camera.position = c2w[:3, 3]
            client.camera.up_direction = -c2w[:3, 1]
            client.camera.look_at = c2w[:3, 3] + c2w[:3, 2] * (scene.near + scene.far) / 2
            client.camera.fov = vertical_fov(scene.intrinsics[index], scene.height)

    def _snap(self, client: Any, state: _ClientState) -> None:
        scene = self.renderer.frames.scene(state.scene)
        position = torch.as_tensor(np.asarray(client.camera.position), dtype=torch.float32)
        index = int((scene.c2w[:, :3, 3] - position).norm(dim=-1).argmin())
        self._move_camera_to(client, state, index)

    def request_of(self, client: Any, state: _ClientState) -> ViewRequest:
        camera = client.camera
        with state.lock:
            return ViewRequest(
                scene=state.scene, wxyz=tuple(float(x) for x in camera.wxyz),
                position=tuple(float(x) for x in camera.position), fov=float(camera.fov),
                aspect=float(camera.aspect), source_views=state.source_views, stride=state.stride,
                preview_stride=max(state.preview_stride, state.stride),
            )

    def _camera_moved(self, client: Any, state: _ClientState) -> None:
        self._hide_frustum_at_lens(client, state)
        if self.progressive is not None:
            self.progressive.submit(client.client_id, self.request_of(client, state))

    # ---- frames -------------------------------------------------------------------------------------------------

    def _deliver(self, client_id: Any, request: ViewRequest, view: RenderedView) -> None:
        with self._clients_lock:
            state = self._clients.get(client_id)
            client = self.server.get_clients().get(client_id) if self.server is not None else None
        if state is None or client is None:
            return  # disconnected while rendering
        self._show(client, state, request, view)
        self.frames_delivered += 1

    def _show(self, client: Any, state: _ClientState, request: ViewRequest, view: RenderedView) -> None:
        if view.error is not None:
            state.gui["status"].content = f"**render failed**: {view.error}"
            return
        state.last, state.last_request = view, request
        layers = [name for name in LAYERS if name in view.layers]
        layer_gui = state.gui["layer"]
        if tuple(layer_gui.options) != tuple(layers):
            layer_gui.options = layers
        layer = state.layer if state.layer in view.layers else "rgb"
        try:
            picture = view.layers[layer]  # drawn when first shown (evaluation.pictures.Layers)
        except Exception as exc:  # a picture that cannot be drawn is a status line, never a dead viewer
            state.gui["status"].content = f"**layer {layer} failed**: {type(exc).__name__}: {exc}"
            return
        if "legend" in state.gui:
            state.gui["legend"].visible = state.gui["highlight"].visible = layer == "semantic"
            chosen = state.gui["highlight"].value
            if layer == "semantic" and chosen != "none" and view.prediction is not None:
                labels = view.prediction.logits[0].argmax(0).cpu().numpy()
                picture = highlight_class(picture, labels, list(self.options.class_names).index(chosen))
        picture = self._with_query(state, view, picture)
        client.scene.set_background_image(picture, format="jpeg")
        self._highlight(client, state, request.scene, view.sources)
        self._show_splats(client, state, request.scene, view.sources)
        sources = ", ".join(str(s) for s in view.sources)
        compared = f"  \nat frame {view.frame}: PSNR {view.psnr:.2f} against it" if view.frame is not None else ""
        state.gui["status"].content = (f"**{view.stage}** (stride {view.stride}): {view.seconds:.2f} s  \n"
                                       f"source views: {sources}{compared}")

    def _show_splats(self, client: Any, state: _ClientState, scene_name: str, sources: Sequence[int]) -> None:
        """The model's Gaussians of the view's sources as splats (hidden with the checkbox), coloured as chosen; sent
        only when the scene, the sources or the colours changed."""
        if "gaussians" not in state.gui:
            return
        if not bool(state.gui["gaussians"].value):
            if state.splats is not None:
                state.splats.visible = False
            return
        colours = str(state.gui["splat_colours"].value)
        query = state.query if colours == "relevancy" else None
        shown = (scene_name, tuple(sources), colours, query,
                 float(state.gui["threshold"].value) if query is not None else None)
        if shown != state.splats_shown:
            splats = self.renderer.gaussians(scene_name, tuple(sources))
            if splats is None:
                return
            if state.splats is not None:
                state.splats.remove()
            try:
                arrays = splat_arrays(splats, colours, self.renderer.label_count,
                                      query.embedding if query is not None else None, shown[4] or 0.5)
            except ConfigError as exc:
                state.gui["query_status"].content = f"**Gaussians not coloured by relevancy**: {exc}"
                arrays = splat_arrays(splats, "rgb", self.renderer.label_count)
            state.splats = client.scene.add_gaussian_splats("/gaussians", **arrays)
            state.splats_shown = shown
        state.splats.visible = True

    def _highlight(self, client: Any, state: _ClientState, scene_name: str, sources: Sequence[int]) -> None:
        for handle in state.highlighted:
            handle.remove()
        state.highlighted = []
        scene = self.renderer.frames.scene(scene_name)
        for index in sources:
            wxyz, position = viser_pose(scene.c2w[index])
            state.highlighted.append(client.scene.add_camera_frustum(
                f"/sources/{index:04d}", fov=vertical_fov(scene.intrinsics[index], scene.height),
                aspect=scene.width / scene.height, scale=self._frustum_scale(scene) * 1.1, color=SOURCE_COLOUR,
                wxyz=wxyz, position=position, **FRUSTUM_LINES,
            ))


def serve_until_stopped(server: ViewerServer, stop: threading.Event) -> None:
    """Print the URL and serve until ``stop`` is set; then stop the server. An interruption (Ctrl-C, SIGTERM: the
    command's handlers raise it) stops the server and goes on up, so the command exits 130 or 143 with one line."""
    print(f"viewer: open {server.url} in a browser (Ctrl-C stops it)", flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        server.stop()
