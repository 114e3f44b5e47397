"""A tiny model (untrained: the viewer renders whatever weights it is given) on the tiny scenes, and its renderer."""

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.data.frames import FrameCache
from gpnerf_core.tools.viewer.camera import vertical_fov, viser_pose
from gpnerf_core.tools.viewer.renderer import SceneRenderer, ViewRequest
from pipeline_check import TINY_MODEL, TINY_SCENES


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(components, renderer) of a tiny GP-NeRF with a class head, on CPU, one thread."""
    import os

    os.environ.setdefault("GPNERF_CACHE", str(tmp_path_factory.mktemp("cache")))
    torch.set_num_threads(1)
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES])
    torch.manual_seed(0)
    components = build_components(cfg)
    components.model.eval()
    frames = FrameCache(components.dataset, torch.device("cpu"))
    renderer = SceneRenderer(components.model, frames, components.view_selector,
                             num_classes=components.classes.num_classes, chunk_rays=256, default_source_views=2)
    return components, renderer


@pytest.fixture
def at_frame():
    """``at_frame(renderer, scene, index, **settings)``: the request of a browser sitting at a frame's pose."""
    return request_at_frame


def request_at_frame(renderer: SceneRenderer, scene_name: str, index: int, **settings) -> ViewRequest:
    """The viser camera a browser would send when it sits exactly at frame ``index`` of the scene."""
    scene = renderer.frames.scene(scene_name)
    wxyz, position = viser_pose(scene.c2w[index])
    values = dict(source_views=2, stride=2, preview_stride=8)
    values.update(settings)
    return ViewRequest(scene=scene_name, wxyz=tuple(wxyz), position=tuple(position),
                       fov=vertical_fov(scene.intrinsics[index], scene.height), aspect=scene.width / scene.height,
                       **values)
