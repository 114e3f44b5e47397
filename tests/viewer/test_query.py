"""Queries in the viewer: a click on the view becomes the query from the view's kept feature map (no render), its
relevancy is blended over every view shown afterwards where it reaches the threshold, a text box appears only with a
text encoder, and an answer takes well under 0.1 s."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from unittest.mock import MagicMock

import numpy as np
import pytest
import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.features.queries import similarity_map
from gpnerf_core.tools.viewer.query import Query, answer, box_query, click_query, relevancy_picture
from gpnerf_core.tools.viewer.server import ViewerOptions, ViewerServer, _ClientState

OPTIONS = dict(host="127.0.0.1", port=0, scene="layout_00", scenes=("layout_00",), stride=2, preview_stride=8,
               source_views=2)


@pytest.fixture
def view(tiny, at_frame):
    """(request, rendered view) of the tiny model at a training frame, the full frame at stride 2."""
    _, renderer = tiny
    scene = renderer.frames.scene("layout_00")
    request = at_frame(renderer, "layout_00", scene.train_frames[1])
    return request, renderer.render("layout_00", renderer.camera(request, multiple=8), 2, 2, "full")


def test_a_click_is_the_feature_of_the_clicked_cell_and_its_map_peaks_there(view):
    _, rendered = view
    features = rendered.prediction.semantic  # GP-NeRF's rendered semantic embedding, [C, 16, 24] of a 32 x 48 view
    query = click_query(rendered.prediction, (0.75, 0.25))  # pixel (36, 8): cell (4, 18) at stride 2
    unit = features[:, 4, 18] / features[:, 4, 18].norm()
    assert torch.allclose(query.embedding, unit, atol=1e-6) and query.label == "pixel (36, 8)"
    similarity = similarity_map(features, query.embedding)
    assert float(similarity[4, 18]) == pytest.approx(float(similarity.max()), abs=1e-6)
    with pytest.raises(ConfigError, match="no view is rendered yet"):
        click_query(None, (0.5, 0.5))


def test_a_dragged_box_is_the_mean_feature_of_its_cells(view):
    _, rendered = view
    features = rendered.prediction.semantic
    query = box_query(rendered.prediction, (0.5, 0.5), (0.25, 0.0))  # any two corners: x 12-24, y 0-16 of 32 x 48
    unit = features / features.norm(dim=0, keepdim=True)
    assert torch.allclose(query.embedding, unit[:, 0:9, 6:13].reshape(features.shape[0], -1).mean(dim=1), atol=1e-6)
    assert query.label == "box (12, 0)-(24, 16)"


def test_the_relevancy_is_blended_where_it_reaches_the_threshold():
    picture = np.full((4, 4, 3), 100, np.uint8)
    similarity = torch.tensor([[0.1, 0.9], [0.5, 1.0]])
    out = relevancy_picture(picture, similarity, 0.5)
    assert (out[:2, :2] == 100).all()  # below the threshold: the picture as it was
    assert not (out[:2, 2:] == 100).all() and not (out[2:, :2] == 100).all()
    assert not np.array_equal(out[2:, 2:], out[2:, :2])  # 1.0 and the threshold in other colours


def test_an_answer_reads_the_kept_feature_map_quickly_and_refuses_another_dimension(view):
    _, rendered = view
    picture = rendered.layers["rgb"]
    query = click_query(rendered.prediction, (0.5, 0.5))
    answered = answer(rendered.prediction, picture, query, 0.5)
    assert answered.picture.shape == picture.shape and 0 < answered.selected <= 1 and answered.peak > 0.99
    assert answered.seconds < 0.1
    with pytest.raises(ConfigError, match="has 3 dimensions and the feature field has"):
        answer(rendered.prediction, picture, Query(torch.ones(3), "text 'x'"), 0.5)


def client_and_state(server):
    """A browser as the server sees it: a viser client whose calls are recorded, and its controls."""
    client = MagicMock()
    state = _ClientState(scene="layout_00")
    server._build_query_gui(client, state)
    state.gui.update({key: SimpleNamespace(value=value, content="", options=(), visible=True) for key, value in
                      (("layer", "rgb"), ("status", ""), ("threshold", 0.5), ("query_status", ""))})
    return client, state


def test_a_click_in_the_viewer_answers_on_the_view_on_screen_without_rendering(tiny, view, monkeypatch):
    _, renderer = tiny
    request, rendered = view
    server = ViewerServer(renderer, ViewerOptions(**OPTIONS))
    client, state = client_and_state(server)
    assert "query_text" not in state.gui  # no text encoder: no text box
    state.last, state.last_request = rendered, request
    renders = []
    monkeypatch.setattr(renderer, "render", lambda *a, **k: renders.append(a))  # a query must not render
    server.query_at(client, state, (0.5, 0.5))
    shown = client.scene.set_background_image.call_args[0][0]
    assert not np.array_equal(shown, rendered.layers["rgb"]) and renders == []
    assert state.gui["query_status"].content.startswith("**query** pixel (24, 16): ")
    assert state.query_seconds < 0.1
    server.query_box(client, state, (0.0, 0.0), (0.2, 0.3))
    assert state.gui["query_status"].content.startswith("**query** box (0, 0)-(10, 10): ")
    server.query_at(client, state, (0.5, 0.5))
    state.gui["threshold"].value = 1.0  # nothing but the clicked cell's own direction reaches 1
    server._show_last(client, state)
    fewer = client.scene.set_background_image.call_args[0][0]
    assert (fewer == rendered.layers["rgb"]).mean() > (shown == rendered.layers["rgb"]).mean()


def test_a_text_box_with_a_text_encoder_and_its_refusals(tiny, view):
    _, renderer = tiny
    request, rendered = view
    channels = int(rendered.prediction.semantic.shape[0])
    server = ViewerServer(renderer, ViewerOptions(**OPTIONS, text_encoder=lambda text: torch.ones(channels)))
    client, state = client_and_state(server)
    assert "query_text" in state.gui
    state.last, state.last_request = rendered, request
    server.query_text(client, state, "a chair")
    assert state.gui["query_status"].content.startswith("**query** 'a chair': ")
    wrong = ViewerServer(renderer, ViewerOptions(**OPTIONS, text_encoder=lambda text: torch.ones(channels + 1)))
    client, state = client_and_state(wrong)
    state.last, state.last_request = rendered, request
    wrong.query_text(client, state, "a chair")
    assert state.gui["query_status"].content.startswith(f"**query refused**: the query embedding has {channels + 1} "
                                                        f"dimensions and the feature field has {channels} channels")


def test_splats_coloured_by_relevancy_where_it_reaches_the_threshold():
    from gpnerf_core.geometry.gaussians.scene import GaussianScene
    from gpnerf_core.tools.viewer.splats import splat_arrays

    count = 4
    features = torch.tensor([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0], [-1.0, 0.0]])
    scene = GaussianScene(means=torch.zeros(count, 3), scales=torch.full((count, 3), 0.01),
                          rotations=torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1), opacities=torch.full((count,), 0.5),
                          harmonics=torch.zeros(count, 3, 1), labels=torch.full((count,), -1), features=features)
    own = splat_arrays(scene, "rgb", 0)["rgbs"]
    coloured = splat_arrays(scene, "relevancy", 0, torch.tensor([1.0, 0.0]), 0.5)["rgbs"]
    assert np.allclose(coloured[2:], own[2:] / 4)  # below the threshold: their own colour, dimmed
    assert not np.allclose(coloured[:2], own[:2] / 4) and not np.allclose(coloured[0], coloured[1])
    field = dataclasses.replace(scene, feature_field=torch.tensor([[0.0, 1.0]] * count))  # the field comes first
    assert np.allclose(splat_arrays(field, "relevancy", 0, torch.tensor([1.0, 0.0]), 0.5)["rgbs"], own / 4)
    with pytest.raises(ConfigError, match="has 3 dimensions and the feature field has 2 channels"):
        splat_arrays(scene, "relevancy", 0, torch.ones(3), 0.5)


def test_the_view_command_gives_the_text_box_a_providers_text_encoder_only():
    from gpnerf_core.commands.view import _text_encoder

    class Provider:
        text_encoder = True

        def encode_text(self, texts):
            return torch.ones(len(texts), 8)

    encoder = _text_encoder(SimpleNamespace(feature_field=SimpleNamespace(provider=Provider())))
    assert torch.equal(encoder("a chair"), torch.ones(8))
    Provider.text_encoder = False
    assert _text_encoder(SimpleNamespace(feature_field=SimpleNamespace(provider=Provider()))) is None
    assert _text_encoder(SimpleNamespace(feature_field=None)) is None
