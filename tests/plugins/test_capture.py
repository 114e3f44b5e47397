"""The ``capture`` dataset: nerfstudio's transforms.json written from embedded scenes reads back as the same scene
(poses, intrinsics, colours, depth, labels), distortion is undone, and every malformed file is one line."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from capture_fixtures import write_capture
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.capture.dataset import CaptureScenes
from gpnerf_plugins.datasets.embedded import CLASS_NAMES, SceneSetParams, generate
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes

TINY = dict(num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=8, height=48, width=64, seed=0)
DISTORTION = (-0.3, 0.08, 0.002, -0.001)


@pytest.fixture(scope="module")
def embedded_scene(tmp_path_factory):
    root = generate(SceneSetParams(**TINY), tmp_path_factory.mktemp("embedded") / "set")
    dataset = EmbeddedScenes(root=str(root), num_train_scenes=1, num_unseen_scenes=0, frames_per_scene=8, height=48,
                             width=64, eval_every=0)
    return dataset.load_scene(dataset.scenes("train")[0])


@pytest.fixture(scope="module")
def capture(embedded_scene, tmp_path_factory):
    return write_capture(embedded_scene, tmp_path_factory.mktemp("captures") / "room")


def load(root, **options):
    dataset = CaptureScenes(root=str(root), height=options.pop("height", 48), width=options.pop("width", 64), **options)
    return dataset, dataset.load_scene(dataset.scenes("train")[0])


def test_a_capture_reads_back_as_the_scene_it_was_written_from(embedded_scene, capture):
    dataset, scene = load(capture)
    assert dataset.class_names == CLASS_NAMES and scene.labelled
    assert torch.allclose(scene.c2w, embedded_scene.c2w, atol=1e-6)
    assert torch.allclose(scene.intrinsics, embedded_scene.intrinsics, atol=1e-5)
    for index in (0, 5):
        mine, truth = scene.load_frame(index), embedded_scene.load_frame(index)
        assert torch.equal(mine.rgb, truth.rgb)
        assert torch.equal(mine.semantic, truth.semantic)
        assert (mine.depth - truth.depth).abs().max() <= 0.0005 + 1e-6  # stored in millimetres
    # bounds from the depth maps: the 1st / 99th percentiles, 10% margin
    depths = torch.cat([embedded_scene.load_frame(i).depth.flatten() for i in range(8)])
    assert scene.near < float(depths[depths > 0].quantile(0.02)) and scene.far > float(depths.quantile(0.98))


def test_every_eighth_frame_from_the_fourth_is_held_out_unless_the_file_lists_splits(capture, tmp_path):
    _, scene = load(capture)
    assert scene.eval_frames == (4,) and scene.train_frames == (0, 1, 2, 3, 5, 6, 7)
    _, scene = load(capture, eval_every=3)
    assert scene.eval_frames == (1, 4, 7)
    listed = _copy(capture, tmp_path, lambda t: t.update(train_filenames=["images/frame_00000.png",
                                                                          "images/frame_00002.png"],
                                                         val_filenames=["images/frame_00007.png"]))
    _, scene = load(listed)
    assert scene.train_frames == (0, 2) and scene.eval_frames == (7,)


def test_opencv_distortion_is_undone(embedded_scene, tmp_path):
    distorted = write_capture(embedded_scene, tmp_path / "lens", distortion=DISTORTION)
    _, scene = load(distorted)
    interior = (slice(6, -6), slice(6, -6))  # the corners the lens pushed outside the frame carry no data
    for index in (2, 5):
        truth, mine = embedded_scene.load_frame(index), scene.load_frame(index)
        raw_labels = np.asarray(Image.open(distorted / "semantics" / f"frame_{index:05d}.png")).astype(np.int64)
        raw_rgb = np.asarray(Image.open(distorted / "images" / f"frame_{index:05d}.png"), dtype=np.float32) / 255
        assert (raw_labels == truth.semantic.numpy())[interior].mean() < 0.975  # the lens moved the edges
        assert float((mine.semantic == truth.semantic)[interior].float().mean()) > 0.985
        # colours: resampled twice (by the fixture's lens and by the loader), so blurred, but in place
        assert float((mine.rgb - truth.rgb)[interior].abs().mean()) < 0.7 * np.abs(raw_rgb - truth.rgb.numpy())[
            interior].mean()


def test_the_undistortion_grid_lands_within_a_hundredth_of_a_pixel():
    """Each undistorted pixel samples the recorded image where the lens put it: kornia's inverse brings it back."""
    from kornia.geometry.calibration import undistort_points

    from gpnerf_plugins.datasets.capture.undistort import Undistorter

    k = np.array([[32.0, 0, 31.5], [0, 32.0, 23.5], [0, 0, 1]])
    grid = Undistorter(k, DISTORTION + (0.0,), 48, 64).grid[0].double()
    recorded = (grid + 1) * torch.tensor([63 / 2, 47 / 2], dtype=torch.float64)
    back = undistort_points(recorded.reshape(-1, 2), torch.from_numpy(k), torch.tensor(DISTORTION, dtype=torch.float64),
                            num_iters=50)
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    assert (back.reshape(48, 64, 2) - torch.stack([u, v], -1).double()).abs().max() < 0.01


def test_per_frame_intrinsics_camera_angle_and_applied_transform(embedded_scene, capture, tmp_path):
    per_frame = write_capture(embedded_scene, tmp_path / "per_frame", per_frame_intrinsics=True)
    _, scene = load(per_frame)
    assert torch.allclose(scene.intrinsics, embedded_scene.intrinsics, atol=1e-5)
    fov = 2 * math.atan(0.5 * 64 / float(embedded_scene.intrinsics[0, 0, 0]))

    def blender(t):
        for key in ("fl_x", "fl_y", "cx", "cy"):
            t.pop(key)
        t["camera_angle_x"] = fov

    _, scene = load(_copy(capture, tmp_path, blender))
    assert torch.allclose(scene.intrinsics[0, 0, 0], embedded_scene.intrinsics[0, 0, 0], rtol=1e-5)
    assert float(scene.intrinsics[0, 0, 2]) == pytest.approx(31.5)

    applied = np.eye(4)[[0, 2, 1, 3]]
    applied[2] *= -1  # ns-process-data's swap of COLMAP's world axes

    def moved(t):
        for frame in t["frames"]:
            frame["transform_matrix"] = (applied @ np.asarray(frame["transform_matrix"])).tolist()
        t["applied_transform"] = applied[:3].tolist()

    _, scene = load(_copy(capture, tmp_path, moved))
    assert torch.allclose(scene.c2w, embedded_scene.c2w, atol=1e-6)


def test_size_scale_and_masks(embedded_scene, capture, tmp_path):
    dataset, scene = load(capture, height=0, width=0, long_side=80, scale=2.0)
    assert (scene.height, scene.width) == (64, 80)  # 48x64 to a long side of 80: 60x80, 60 rounded to 16s
    assert torch.allclose(scene.c2w[:, :3, 3], 2 * embedded_scene.c2w[:, :3, 3], atol=1e-5)
    assert float(scene.intrinsics[0, 0, 0]) == pytest.approx(32 * 80 / 64) and float(scene.intrinsics[0, 1, 1]) == \
        pytest.approx(32 * 64 / 48)
    frame, truth = scene.load_frame(0), embedded_scene.load_frame(0)
    assert frame.rgb.shape == (64, 80, 3) and float(frame.depth.max()) == pytest.approx(2 * float(truth.depth.max()),
                                                                                       rel=0.02)
    mask = np.full((48, 64), 255, np.uint8)
    mask[:, :32] = 0

    def masked(t):
        (Path(t["_folder"]) / "masks").mkdir()
        Image.fromarray(mask).save(Path(t["_folder"]) / "masks" / "m.png")
        for frame in t["frames"]:
            frame["mask_path"] = "masks/m.png"

    dataset, scene = load(_copy(capture, tmp_path, masked))
    frame = scene.load_frame(0)
    assert bool((frame.semantic[:, :32] == 255).all()) and bool((frame.depth[:, :32] == 0).all())
    assert torch.equal(frame.semantic[:, 32:], truth.semantic[:, 32:])
    assert torch.equal(frame.valid, torch.from_numpy(mask > 0))
    # training draws its rays only through the pixels the mask keeps
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.training.sampler import StepSampler
    from gpnerf_plugins.view_selectors.nearest import NearestViews

    sampler = StepSampler(FrameCache(dataset, torch.device("cpu")), NearestViews(), scene_names=[scene.name],
                          num_source_views=2, rays_per_view=2000, targets_per_step=1, seed=0)
    view = sampler._target_view(scene.name, 0, seed=3)
    assert view.pixels.shape[0] == 32 * 48 and bool((view.pixels[:, 0] >= 32).all())


def test_a_capture_without_labels_is_an_unlabelled_scene(embedded_scene, tmp_path):
    plain = write_capture(embedded_scene, tmp_path / "plain", labels=False)
    dataset, scene = load(plain)
    assert dataset.class_names == () and not scene.labelled
    assert bool((scene.load_frame(0).semantic == dataset.ignore_index).all())


def test_several_captures_under_one_root_and_the_scene_lists(embedded_scene, capture, tmp_path):
    root = tmp_path / "captures"
    for name in ("kitchen", "hall"):
        shutil.copytree(capture, root / name)
    dataset = CaptureScenes(root=str(root), height=48, width=64, unseen_scenes=["hall"])
    assert dataset.scenes("train") == ("kitchen",) and dataset.scenes("unseen") == ("hall",)
    with pytest.raises(DataError, match="attic"):
        CaptureScenes(root=str(root), scenes=["attic"]).scenes("train")


@pytest.mark.parametrize("change,message", [
    (lambda t: t["frames"][0].pop("transform_matrix"), "frame 'images/frame_00000.png' has no 'transform_matrix'"),
    (lambda t: t.update(camera_model="FISHEYE"), "camera_model='FISHEYE'; expected one of PINHOLE, SIMPLE_PINHOLE"),
    (lambda t: t["frames"][1].update(file_path="../../etc/passwd"), "leaves the capture folder"),
    (lambda t: t["frames"][2]["transform_matrix"][0].__setitem__(3, float("nan")), "holds NaN or Inf"),
    (lambda t: t["frames"][2]["transform_matrix"][0].__setitem__(0, 3.0), "rotation not orthonormal"),
    (lambda t: t.update(w=100), "image is 64x48 but w=100"),
    (lambda t: t.pop("fl_x"), "no intrinsics"),
    (lambda t: t.update(frames=[]), "'frames' is missing or empty"),
    (lambda t: t["frames"][3].update(file_path="images/nothing.png"), "nothing.png"),
])
def test_a_malformed_transforms_file_is_one_line_naming_it(capture, tmp_path, change, message):
    broken = _copy(capture, tmp_path, change)
    with pytest.raises(DataError) as error:
        load(broken)
    text = str(error.value)
    assert message in text and "\n" not in text
    assert str(broken) in text


@pytest.mark.parametrize("options,message", [
    (dict(root=""), "dataset.root is empty"),
    (dict(root="x", height=50, width=64), "dataset.height=50"),
    (dict(root="x", near=0.5, far=0.0), "dataset.near=0.5"),
    (dict(root="x", scale=0.0), "dataset.scale=0.0"),
])
def test_bad_options_are_refused_before_any_file_is_read(options, message):
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        CaptureScenes(**options)


def test_a_capture_trains_and_evaluates_through_the_command_line(capture, tmp_path):
    from pipeline_check import TINY_MODEL, gpnerf

    model = [o for o in TINY_MODEL if not o.startswith("eval.")] + ["eval.save_images=0"]
    result = gpnerf("run", "+head=unet", "+loss=dgs", "dataset=capture", f"dataset.root={capture}",
                    "dataset.height=32", "dataset.width=48", *model, f"out_dir={tmp_path / 'run'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["eval"]["train_heldout"]["count/images"] == 1
    assert math.isfinite(metrics["eval"]["train_heldout"]["psnr/clamped"])


def _copy(capture: Path, tmp_path: Path, change) -> Path:
    """A copy of ``capture`` whose transforms.json ``change`` edited (it may use ``t["_folder"]``)."""
    folder = tmp_path / f"copy_{len(list(tmp_path.glob('copy_*')))}"
    shutil.copytree(capture, folder)
    transforms = json.loads((folder / "transforms.json").read_text())
    transforms["_folder"] = str(folder)
    change(transforms)
    transforms.pop("_folder")
    (folder / "transforms.json").write_text(json.dumps(transforms))
    return folder



def test_data_check_reads_every_frame_of_every_capture(capture, tmp_path, capsys):
    from gpnerf_core.cli import main

    assert main(["data", "check", str(capture), "--layout", "capture"]) == 0
    out = capsys.readouterr().out
    assert "captures: 1" in out and "labelled captures: 1" in out and "frames: 8" in out and "problems: none" in out
    broken = _copy(capture, tmp_path, lambda t: None)
    (broken / "images" / "frame_00006.png").write_bytes(b"not a png")
    assert main(["data", "check", str(broken), "--layout", "capture"]) == 1
    out = capsys.readouterr().out
    assert "frame_00006.png: unreadable image" in out and "problems (1)" in out


def test_bounds_from_the_sparse_points_of_ply_file_path(embedded_scene, tmp_path):
    """A nerfstudio capture without depth maps: its sparse points (in the file's world, applied_transform included)
    give the bounds."""
    import pycolmap

    capture = write_capture(embedded_scene, tmp_path / "sparse", depth=False, labels=False)
    frame = embedded_scene.load_frame(0)
    k, c2w = frame.intrinsics.double(), frame.c2w.double()
    v, u = torch.meshgrid(torch.arange(0, 48, 4.0), torch.arange(0, 64, 4.0), indexing="ij")
    depth = frame.depth[::4, ::4].double()
    rays = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1).double()
    world = (rays * depth[..., None]).reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
    applied = np.eye(4)[[0, 2, 1, 3]]
    applied[2] *= -1
    cloud = pycolmap.Reconstruction()
    for point in world[depth.reshape(-1) > 0].numpy() @ applied[:3, :3].T:
        cloud.add_point3D(point, pycolmap.Track(), np.zeros(3, np.uint8))
    cloud.export_PLY(str(capture / "sparse_pc.ply"))
    transforms = json.loads((capture / "transforms.json").read_text())
    for entry in transforms["frames"]:
        entry["transform_matrix"] = (applied @ np.asarray(entry["transform_matrix"])).tolist()
    transforms.update(applied_transform=applied[:3].tolist(), ply_file_path="sparse_pc.ply")
    (capture / "transforms.json").write_text(json.dumps(transforms))
    _, scene = load(capture)
    seen = depth[depth > 0]
    # frame 0 sees these points at their true depths: its bounds (0.9 x 1st, 1.1 x 99th percentile) hold them
    assert 0 < scene.near < float(seen.quantile(0.01)) and scene.far > float(seen.quantile(0.99))
    assert scene.far < 3 * float(seen.max())
    assert torch.allclose(scene.c2w, embedded_scene.c2w, atol=1e-6)
    points = scene.sparse_points()  # what a per-scene Gaussian family starts from: in the poses' world
    assert points.count == int((depth > 0).sum()) and torch.equal(points.rgb, torch.zeros(points.count, 3))
    assert torch.cdist(points.xyz.double(), world[depth.reshape(-1) > 0]).min(dim=1).values.max() < 1e-5
    assert load(write_capture(embedded_scene, tmp_path / "none", labels=False))[1].sparse_points is None
    transforms["ply_file_path"] = "missing.ply"
    (capture / "transforms.json").write_text(json.dumps(transforms))
    with pytest.raises(DataError, match="missing.ply: unreadable point cloud"):
        load(capture)


def _binary_ply(xyz: np.ndarray, declared: int | None = None) -> bytes:
    """A little-endian PLY of ``xyz`` with black colours, as pycolmap writes one (``declared``: the header's count)."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz) if declared is None else declared}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rows = np.zeros(len(xyz), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"] = xyz
    return header + rows.tobytes()


_POINTS = np.array([[0.1, 0.2, 1.5], [0.3, -0.1, 2.0], [-0.2, 0.0, 1.8]])


@pytest.mark.parametrize("content, message", [
    (bytes(range(256)) * 3, "unreadable point cloud .*x, y, z properties missing"),
    (_binary_ply(np.array([[0.1, 0.2, 1.5], [np.nan, 0.0, 1.0], [0.3, np.inf, 2.0]])),
     "2 of 3 sparse points have NaN or Inf coordinates; expected finite"),
    (b"ply\nformat ascii 1.0\nelement face 2\nproperty float x\nend_header\n1\n2\n", "unreadable point cloud"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float a\nproperty float b\nend_header\n1 2\n3 4\n",
     "unreadable point cloud"),
    (_binary_ply(_POINTS, declared=5), "unreadable point cloud .*Unexpected end of PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n0 0 1\n", "holds 1 of the 5 points its header declares"),
])
def test_a_bad_sparse_points_ply_is_named_at_read_time_and_by_the_data_checks(capture, tmp_path, capsys, content,
                                                                               message):
    """A capture with depth maps reads its bounds from them, so only the checks and the Gaussian family's
    initialisation read ``sparse_points.ply``: both name the file (was: "problems: none", then NaN at step 0)."""
    from gpnerf_core.cli import main

    folder = _copy(capture, tmp_path, lambda t: t.update(ply_file_path="sparse_points.ply"))
    (folder / "sparse_points.ply").write_bytes(content)
    dataset, scene = load(folder)
    with pytest.raises(DataError, match=f"sparse_points.ply: {message}") as caught:
        scene.sparse_points()
    assert "\n" not in str(caught.value)
    problems = dataset.check_files(dataset.scenes("train"), "quick")
    assert any("sparse_points.ply" in problem and re.search(message, problem) for problem in problems), problems
    assert main(["data", "check", str(folder), "--layout", "capture"]) == 1
    out = capsys.readouterr().out
    assert "sparse_points.ply" in out and "problems: none" not in out


def test_a_good_sparse_points_ply_passes_the_checks(capture, tmp_path):
    folder = _copy(capture, tmp_path, lambda t: t.update(ply_file_path="sparse_points.ply"))
    (folder / "sparse_points.ply").write_bytes(_binary_ply(_POINTS))
    dataset, scene = load(folder)
    assert dataset.check_files(dataset.scenes("train"), "quick") == []
    assert scene.sparse_points().count == 3


def _eight_bit_depth(t):
    path = Path(t["_folder"]) / t["frames"][2]["depth_file_path"]
    Image.fromarray(np.full((48, 64), 200, dtype=np.uint8)).save(path)


def _camera_far_away(t):
    t["frames"][5]["transform_matrix"][0][3] = 1e30


def _depth_beyond_far(t):
    path = Path(t["_folder"]) / t["frames"][1]["depth_file_path"]
    Image.fromarray(np.full((48, 64), 60000, dtype=np.uint16)).save(path)  # 60 m, far beyond the room


@pytest.mark.parametrize("change, level, message", [
    (_eight_bit_depth, "full", "depth stored in 8 bits (at most 255 units); expected a 16-bit PNG"),
    (_camera_far_away, "quick", "frame 5: camera centre 1e+30 m from the scene's median centre, more than 10000 x far = 8e+04 m"),
    (_depth_beyond_far, "full", "frame 1: every known depth is beyond far="),
])
def test_data_that_loads_but_cannot_be_right_is_refused_by_the_checks(capture, tmp_path, change, level, message):
    dataset = CaptureScenes(root=str(_copy(capture, tmp_path, change)), height=48, width=64, near=0.1, far=8.0)
    problems = dataset.check_files(dataset.scenes("train"), level)
    assert any(message in problem for problem in problems), problems


def _label_out_of_range(t):
    path = Path(t["_folder"]) / t["frames"][3]["semantic_file_path"]
    labels = np.asarray(Image.open(path)).copy()
    labels[0, 0] = 77  # 9 classes, ignore index 255
    Image.fromarray(labels).save(path)


def test_a_label_id_outside_the_classes_is_named_with_its_file_when_the_scene_loads_and_when_read(capture, tmp_path):
    """Issue 55: a training frame the quick check did not decode was refused only when training read it, without
    the file; its label ids are now read when the scene loads (quick or full), and checked whenever read."""
    folder = _copy(capture, tmp_path, _label_out_of_range)
    expected = (f"{folder / 'semantics' / 'frame_00003.png'}: class id 77 outside the 9 classes 0..8 of "
                f"{folder / 'classes.json'} and not its ignore_index=255")
    with pytest.raises(DataError, match=expected.replace(".", r"\.")):
        load(folder)  # dataset.validate=quick: before any training
    _, scene = load(folder, validate="off")
    scene.load_frame(2)
    with pytest.raises(DataError, match=expected.replace(".", r"\.")):
        scene.load_frame(3)
