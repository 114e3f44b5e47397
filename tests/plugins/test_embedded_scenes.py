"""Embedded pybullet scenes: layout on disk, determinism, cache, multi-view consistency, the dataset plugin."""

from __future__ import annotations

import dataclasses
import filecmp
import inspect
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import make_plugin_manager
from gpnerf_core.types import Frame
from gpnerf_plugins.datasets.embedded import (
    CLASS_NAMES,
    GENERATOR_VERSION,
    IGNORE_INDEX,
    SEQUENCE,
    SceneSetParams,
    cache_folder,
    generate,
)
from gpnerf_plugins.datasets.embedded import generation as generate_module
from gpnerf_plugins.datasets.embedded.generation import check_params, ensure_generated
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes, EmbeddedScenesConfig
from gpnerf_plugins.datasets.replica.layout import ReplicaSequence

TINY = dict(num_train_scenes=1, num_unseen_scenes=1, frames_per_scene=12, height=48, width=64, seed=0)


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory) -> Path:
    return generate(SceneSetParams(**TINY), tmp_path_factory.mktemp("embedded") / "set")


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def test_replica_layout_files_and_dtypes(tiny_set):
    assert (tiny_set / "README.md").is_file()
    info = json.loads((tiny_set / "classes.json").read_text())
    assert info["class_names"] == list(CLASS_NAMES) and info["ignore_index"] == IGNORE_INDEX == 255
    assert info["generator_version"] == GENERATOR_VERSION and info["seed"] == 0
    assert info["scenes"] == {"train": ["layout_00"], "unseen": ["unseen_00"]}
    assert 6 <= len(CLASS_NAMES) <= 9
    readme = (tiny_set / "README.md").read_text()
    assert all(name in readme for name in CLASS_NAMES)
    for scene in ("layout_00", "unseen_00"):
        seq = tiny_set / scene / SEQUENCE
        rows = (seq / "traj_w_c.txt").read_text().splitlines()
        assert len(rows) == 12 and all(len(r.split()) == 16 for r in rows)
        for i in range(12):
            rgb = np.asarray(Image.open(seq / "rgb" / f"rgb_{i}.png"))
            depth = np.asarray(Image.open(seq / "depth" / f"depth_{i}.png"))
            cls = np.asarray(Image.open(seq / "semantic_class" / f"semantic_class_{i}.png"))
            ins = np.asarray(Image.open(seq / "semantic_instance" / f"semantic_instance_{i}.png"))
            assert rgb.dtype == np.uint8 and rgb.shape == (48, 64, 3)
            assert depth.dtype == np.uint16 and depth.shape == (48, 64)
            assert cls.dtype == np.uint8 and ins.dtype == np.uint16
            valid = cls != IGNORE_INDEX
            assert (cls[valid] < len(CLASS_NAMES)).all()
            assert ((depth > 0) == valid).all(), "depth is 0 exactly where nothing is hit"
            assert (ins[~valid] == 0).all()
            assert rgb.std() > 10, "frames must be textured, not flat"
    assert not list(tiny_set.parent.glob(".set.tmp-*")), "temporary folder left behind"


def test_classes_and_instances_cover_the_scene(tiny_set):
    seq = ReplicaSequence(tiny_set / "layout_00" / SEQUENCE)
    classes, instances = set(), set()
    for i in range(seq.num_frames):
        frame = seq.load_frame(i)
        classes |= set(frame.semantic.unique().tolist())
        instances |= set(frame.instance.unique().tolist())
    for name in ("floor", "wall", "table"):
        assert CLASS_NAMES.index(name) in classes
    assert len(classes - {IGNORE_INDEX}) >= 5
    assert 0 in instances and len(instances) >= 4


def test_reader_reproduces_depth_mm_and_hfov_intrinsics(tiny_set):
    seq = ReplicaSequence(tiny_set / "unseen_00" / SEQUENCE)
    frame = seq.load_frame(5)
    png = np.asarray(Image.open(tiny_set / "unseen_00" / SEQUENCE / "depth" / "depth_5.png"))
    assert np.array_equal(np.rint(frame.depth.numpy().astype(np.float64) * 1000).astype(np.uint16), png)
    expected = torch.tensor([[32.0, 0.0, 31.5], [0.0, 32.0, 23.5], [0.0, 0.0, 1.0]])
    assert torch.allclose(frame.intrinsics, expected)


def test_same_seed_gives_identical_bytes_and_another_seed_differs(tiny_set, tmp_path):
    again = generate(SceneSetParams(**TINY), tmp_path / "again")
    assert _files(again) == _files(tiny_set)
    match, mismatch, errors = filecmp.cmpfiles(tiny_set, again, [str(p) for p in _files(tiny_set)], shallow=False)
    assert not mismatch and not errors and len(match) == len(_files(tiny_set))
    other = generate(SceneSetParams(**{**TINY, "seed": 1}), tmp_path / "other")
    seq = Path("layout_00") / SEQUENCE
    assert (other / seq / "traj_w_c.txt").read_bytes() != (tiny_set / seq / "traj_w_c.txt").read_bytes()
    assert (other / seq / "rgb" / "rgb_0.png").read_bytes() != (tiny_set / seq / "rgb" / "rgb_0.png").read_bytes()


def _points_in_b(a: Frame, b: Frame, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """a's valid pixels unprojected with a's depth and intrinsics ``k``, in b's camera frame.

    Returns (points ``[N, 3]`` in b's camera coordinates, a's valid-depth mask ``[H, W]``).
    """
    height, width = a.depth.shape
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    depth = a.depth.double()
    valid = depth > 0
    cam = torch.stack([(u - k[0, 2]) / k[0, 0] * depth, (v - k[1, 2]) / k[1, 1] * depth, depth], -1)[valid]
    world = cam @ a.c2w.double()[:3, :3].T + a.c2w.double()[:3, 3]
    w2c = torch.linalg.inv(b.c2w.double())
    return world @ w2c[:3, :3].T + w2c[:3, 3], valid


def _reprojection(a: Frame, b: Frame) -> tuple[float, float, float, float]:
    """Project frame a's pixels into b with a's depth.

    Returns (co-visible fraction of a's valid pixels, depth agreement, class agreement, instance agreement);
    co-visible pixels land inside b on a surface with no closer surface in front (an occluded point is not
    co-visible), and agreement is over co-visible pixels.
    """
    kb = b.intrinsics.double()
    height, width = a.depth.shape
    in_b, valid = _points_in_b(a, b, a.intrinsics.double())
    z = in_b[:, 2]
    ub = torch.round(kb[0, 0] * in_b[:, 0] / z + kb[0, 2]).long()
    vb = torch.round(kb[1, 1] * in_b[:, 1] / z + kb[1, 2]).long()
    inside = (z > 0) & (ub >= 0) & (ub < width) & (vb >= 0) & (vb < height)
    ub, vb, z = ub[inside], vb[inside], z[inside]
    depth_b = b.depth.double()[vb, ub]
    tolerance = 0.03 * z
    covisible = (depth_b > 0) & (depth_b > z - tolerance)
    agree_depth = (depth_b - z).abs() < tolerance
    cls_a, cls_b = a.semantic[valid][inside], b.semantic[vb, ub]
    ins_a, ins_b = a.instance[valid][inside], b.instance[vb, ub]
    n = max(covisible.sum().item(), 1)
    return (
        n / valid.sum().item(),
        (agree_depth & covisible).sum().item() / n,
        ((cls_a == cls_b) & covisible).sum().item() / n,
        ((ins_a == ins_b) & covisible).sum().item() / n,
    )


def test_multi_view_reprojection_consistency(tiny_set):
    """Poses, intrinsics and depth agree across views: the check of the OpenGL -> OpenCV conversion."""
    for scene in ("layout_00", "unseen_00"):
        seq = ReplicaSequence(tiny_set / scene / SEQUENCE)
        for i, j in ((0, 1), (4, 5), (7, 6), (11, 0)):
            covisible, depth_ok, class_ok, instance_ok = _reprojection(seq.load_frame(i), seq.load_frame(j))
            assert covisible > 0.4, (scene, i, j, covisible)
            assert depth_ok > 0.9 and class_ok > 0.9 and instance_ok > 0.9, (scene, i, j, depth_ok, class_ok, instance_ok)


def test_reprojection_check_rejects_an_opengl_pose(tiny_set):
    """The consistency check is sharp: the same frames with OpenGL (y up, z back) poses fail it."""
    seq = ReplicaSequence(tiny_set / "layout_00" / SEQUENCE)
    a, b = seq.load_frame(0), seq.load_frame(1)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    b_gl = dataclasses.replace(b, c2w=b.c2w @ flip)
    covisible, depth_ok, class_ok, _ = _reprojection(a, b_gl)
    assert not (covisible > 0.4 and depth_ok > 0.9 and class_ok > 0.9)
    shifted = dataclasses.replace(b, intrinsics=b.intrinsics + torch.tensor([[0, 0, 2.0], [0, 0, 0], [0, 0, 0]]))
    assert _reprojection(a, shifted)[1] < _reprojection(a, b)[1]


def _median_depth_residual(a: Frame, b: Frame, shift: tuple[float, float]) -> float:
    """Median relative error between a's depth reprojected into b and b's bilinearly sampled depth.

    Both cameras use a's intrinsics with the principal point moved by ``shift`` pixels.
    """
    k = a.intrinsics.double().clone()
    k[0, 2] += shift[0]
    k[1, 2] += shift[1]
    height, width = a.depth.shape
    in_b, _ = _points_in_b(a, b, k)
    z = in_b[:, 2]
    ub, vb = k[0, 0] * in_b[:, 0] / z + k[0, 2], k[1, 1] * in_b[:, 1] / z + k[1, 2]
    inside = (z > 0) & (ub >= 0) & (ub <= width - 1) & (vb >= 0) & (vb <= height - 1)
    ub, vb, z = ub[inside], vb[inside], z[inside]
    u0, v0 = ub.floor().long().clamp(max=width - 2), vb.floor().long().clamp(max=height - 2)
    fu, fv = ub - u0, vb - v0
    db = b.depth.double()
    corners = [db[v0, u0], db[v0, u0 + 1], db[v0 + 1, u0], db[v0 + 1, u0 + 1]]
    all_hit = torch.stack(corners).gt(0).all(0)
    weights = [(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv]
    sampled = sum(c * w for c, w in zip(corners, weights))
    return ((sampled - z).abs() / z)[all_hit].median().item()


def test_pixel_centres_are_at_integers(tiny_set):
    """cx = (W-1)/2, cy = (H-1)/2 is exact: a half-pixel shift of either makes reprojection clearly worse."""
    seq = ReplicaSequence(tiny_set / "layout_00" / SEQUENCE)
    a, b = seq.load_frame(4), seq.load_frame(5)
    exact = _median_depth_residual(a, b, (0.0, 0.0))
    assert exact < 0.002
    for shift in ((0.5, 0.0), (-0.5, 0.0), (0.0, 0.5), (0.0, -0.5)):
        assert _median_depth_residual(a, b, shift) > 3 * exact, shift


def test_dataset_generates_lazily_once_into_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    params = {**TINY, "frames_per_scene": 6}
    dataset = EmbeddedScenes(**params, eval_every=3)
    folder = cache_folder(SceneSetParams(**params))
    assert not folder.exists(), "constructing the dataset must not render"
    assert folder.parent == tmp_path / "cache" / "embedded_scenes" and folder.name.startswith(f"v{GENERATOR_VERSION}-")
    assert dataset.scenes("train") == ("layout_00",) and dataset.scenes("unseen") == ("unseen_00",)
    assert not folder.exists()
    scene = dataset.load_scene("layout_00")
    assert (folder / "classes.json").is_file()
    stamps = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}

    def no_render(*args, **kwargs):
        raise AssertionError("the cached set was rendered again")

    monkeypatch.setattr(generate_module, "render_scene", no_render)
    second = EmbeddedScenes(**params, eval_every=3)
    assert second.load_scene("unseen_00").num_frames == 6
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()} == stamps
    assert scene.train_frames == (0, 2, 3, 5) and scene.eval_frames == (1, 4)
    assert cache_folder(SceneSetParams(**{**params, "seed": 1})) != folder


def test_interrupted_generation_leaves_nothing_behind(tmp_path, monkeypatch):
    real = generate_module.render_scene
    calls = []

    def fail_on_second_scene(folder, params, split, index):
        calls.append(split)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(folder, params, split, index)

    monkeypatch.setattr(generate_module, "render_scene", fail_on_second_scene)
    with pytest.raises(KeyboardInterrupt):
        generate(SceneSetParams(**{**TINY, "frames_per_scene": 2}), tmp_path / "set")
    assert calls == ["train", "unseen"]
    assert list(tmp_path.iterdir()) == []


def test_dataset_scenes_frames_and_bounds(tiny_set):
    dataset = EmbeddedScenes(root=str(tiny_set), **TINY)
    assert dataset.class_names == CLASS_NAMES and dataset.ignore_index == 255 and dataset.num_classes == len(CLASS_NAMES)
    for name in dataset.scenes("train") + dataset.scenes("unseen"):
        scene = dataset.load_scene(name)
        assert scene.name == name and (scene.height, scene.width) == (48, 64)
        assert not set(scene.train_frames) & set(scene.eval_frames)
        assert scene.eval_frames == (3, 9) and len(scene.train_frames) == 10
        frame = scene.load_frame(scene.eval_frames[0])
        hit = frame.depth > 0
        assert float(frame.depth[hit].min()) > scene.near and float(frame.depth.max()) < scene.far
        assert torch.equal(frame.c2w, scene.c2w[scene.eval_frames[0]])
    with pytest.raises(ConfigError, match="train, unseen"):
        dataset.scenes("val")
    with pytest.raises(ConfigError, match="layout_00"):
        dataset.load_scene("layout_07")


def test_explicit_root_with_other_parameters_is_refused(tiny_set, tmp_path):
    with pytest.raises(ConfigError, match="seed"):
        EmbeddedScenes(root=str(tiny_set), **{**TINY, "seed": 3}).load_scene("layout_00")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("x")
    with pytest.raises(DataError, match="classes.json"):
        EmbeddedScenes(root=str(tmp_path / "junk"), **TINY).load_scene("layout_00")


def test_bad_config_values_raise_config_errors():
    with pytest.raises(ConfigError, match="frames_per_scene"):
        EmbeddedScenes(frames_per_scene=1)
    with pytest.raises(ConfigError, match="eval_every"):
        EmbeddedScenes(eval_every=1)
    with pytest.raises(ConfigError, match="near"):
        EmbeddedScenes(near=2.0, far=1.0)


def test_registered_spec_matches_the_constructor_and_does_not_render(tmp_path, monkeypatch):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path))
    registry = collect(make_plugin_manager(builtins=("gpnerf_plugins.datasets.plugin",), autoload=False))
    assert not registry.problems and "embedded" in registry.names("dataset")
    fields = {
        f.name: f.default if f.default is not dataclasses.MISSING else tuple(f.default_factory())
        for f in dataclasses.fields(EmbeddedScenesConfig)
    }
    assert fields.pop("name") == "embedded"
    signature = inspect.signature(EmbeddedScenes.__init__).parameters
    assert {k: signature[k].default for k in fields} == fields
    dataset = registry.build("dataset", {"name": "embedded", **TINY})
    assert isinstance(dataset, EmbeddedScenes)
    assert not any(tmp_path.iterdir())


def test_scene_lists_choose_among_the_generated_layouts():
    dataset = EmbeddedScenes(num_train_scenes=3, num_unseen_scenes=1, scenes=["layout_02"], unseen_scenes=["layout_00"])
    assert dataset.scenes("train") == ("layout_02",) and dataset.scenes("unseen") == ("layout_00",)
    tuned = EmbeddedScenes(num_train_scenes=3, num_unseen_scenes=1, scenes=["unseen_00"])  # fine-tuning on it
    assert tuned.scenes("train") == ("unseen_00",) and tuned.scenes("unseen") == ()
    with pytest.raises(ConfigError, match=r"dataset.scenes has 'kitchen'; the embedded set generates layout_00, "
                                          r"layout_01, unseen_00"):
        EmbeddedScenes(num_train_scenes=2, scenes=["kitchen"])


def test_a_damaged_cached_set_is_set_aside_and_rendered_again(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    params = SceneSetParams(**{**TINY, "frames_per_scene": 2})
    folder = ensure_generated(params)
    (folder / "classes.json").write_text("{ not json")
    again = ensure_generated(params)
    assert again == folder and check_params(folder, params)["parameters"] == params.as_dict()
    aside = [p for p in folder.parent.iterdir() if p.name.startswith(f"{folder.name}.damaged-")]
    assert len(aside) == 1 and (aside[0] / "classes.json").read_text() == "{ not json"
    assert "is damaged" in capsys.readouterr().err
