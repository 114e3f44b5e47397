"""``data import-colmap``: COLMAP models written by pycolmap itself (binary and text) from known cameras import to the
true poses (OpenGL), intrinsics and near/far; several models -> the largest; distorted models are undistorted; every
refusal is one line with exit 2 and nothing half-written."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from gpnerf_core.cli import main as cli_main
from gpnerf_core.errors import DataError
from gpnerf_plugins.datasets.capture.colmap_import import (
    DEPTH_MARGIN,
    FAR_PERCENTILE,
    NEAR_PERCENTILE,
    camera_keys,
    import_colmap,
)
from gpnerf_plugins.datasets.capture.dataset import read_sparse_points
from gpnerf_plugins.datasets.capture.staging import staged
from gpnerf_plugins.datasets.capture.transforms import read_transforms
from gpnerf_plugins.datasets.embedded.trajectory import look_at

OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
WIDTH, HEIGHT = 64, 48


def make_camera(model: str, params: list[float], width: int = WIDTH, height: int = HEIGHT) -> pycolmap.Camera:
    camera = pycolmap.Camera.create_from_model_id(1, getattr(pycolmap.CameraModelId, model), 1.0, width, height)
    camera.params = params
    return camera


def build_model(camera: pycolmap.Camera, names: list[str], seed: int = 0) -> tuple[pycolmap.Reconstruction, dict]:
    """A reconstruction of ``names`` on an arc 4 m from a cube of points, projected through ``camera``.

    Returns the model and, per image name, the true OpenCV camera-to-world and the depths of the points it observes.
    """
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.0, 1.0, size=(400, 3))
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(camera)
    seen, poses = {}, {}
    for image_id, (name, angle) in enumerate(zip(names, np.linspace(0.0, 1.0, len(names))), start=1):
        eye = np.array([4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.0 + 0.2 * angle])
        c2w = look_at(eye, rng.normal(0.0, 0.05, 3))
        w2c = np.linalg.inv(c2w)
        in_camera = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = camera.img_from_cam(in_camera)
        inside = (in_camera[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (
            uv[:, 1] < camera.height)
        ids = np.flatnonzero(inside)
        image = pycolmap.Image(name=name, keypoints=uv[ids], camera_id=camera.camera_id, image_id=image_id)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        seen[image_id] = {int(j): k for k, j in enumerate(ids)}
        poses[name] = (image_id, c2w, in_camera[:, 2])
    truth = {name: {"c2w": c2w, "depths": []} for name, (_, c2w, _) in poses.items()}
    for j, xyz in enumerate(points):
        track = pycolmap.Track()
        for image_id, index in seen.items():
            if j in index:
                track.add_element(image_id, index[j])
        if track.length() >= 2:
            model.add_point3D(xyz, track)
            for name, (image_id, _, depths) in poses.items():
                if j in seen[image_id]:
                    truth[name]["depths"].append(depths[j])
    model.update_point_3d_errors()
    return model, truth


def write_images(folder: Path, names: list[str], width: int = WIDTH, height: int = HEIGHT, seed: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for name in names:
        Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8)).save(folder / name)


def write_model(model: pycolmap.Reconstruction, folder: Path, kind: str) -> Path:
    folder.mkdir(parents=True)
    model.write(folder) if kind == "bin" else model.write_text(folder)
    return folder


def run_cli(capsys, *args) -> tuple[int, str]:
    code = cli_main(["data", "import-colmap", *map(str, args)])
    return code, capsys.readouterr().err.strip()


NAMES = [f"img_{i}.png" for i in range(5)]
OPENCV_PARAMS = [52.0, 50.5, 31.7, 24.3, -0.04, 0.01, 0.001, -0.002]


@pytest.mark.parametrize("kind", ["bin", "txt"])
def test_a_model_imports_to_the_true_poses_intrinsics_and_depth_bounds(tmp_path, kind):
    model, truth = build_model(make_camera("OPENCV", OPENCV_PARAMS), NAMES)
    sparse = write_model(model, tmp_path / "sparse" / "0", kind)
    write_images(tmp_path / "images", NAMES)
    transforms = import_colmap(sparse, tmp_path / "images", tmp_path / "scene")
    assert json.loads((tmp_path / "scene" / "transforms.json").read_text()) == transforms

    expected = dict(zip(["fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"], OPENCV_PARAMS))
    assert transforms["camera_model"] == "OPENCV" and (transforms["w"], transforms["h"]) == (WIDTH, HEIGHT)
    assert {key: transforms[key] for key in expected} == pytest.approx(expected, abs=1e-9)
    assert [f["file_path"] for f in transforms["frames"]] == [f"images/{n}" for n in NAMES]
    for frame, name in zip(transforms["frames"], NAMES):
        np.testing.assert_allclose(frame["transform_matrix"], truth[name]["c2w"] @ OPENGL, atol=1e-6)
        depths = np.array(truth[name]["depths"])
        assert len(depths) >= 20
        low, high = np.percentile(depths, [NEAR_PERCENTILE, FAR_PERCENTILE])
        assert frame["near"] == pytest.approx((1 - DEPTH_MARGIN) * low, rel=1e-6)
        assert frame["far"] == pytest.approx((1 + DEPTH_MARGIN) * high, rel=1e-6)
        assert (1 - DEPTH_MARGIN) * depths.min() <= frame["near"] < depths.min() + 0.1
        assert depths.max() - 0.1 < frame["far"] <= (1 + DEPTH_MARGIN) * depths.max()
        assert (tmp_path / "scene" / frame["file_path"]).read_bytes() == (tmp_path / "images" / name).read_bytes()

    summary = transforms["gpnerf_summary"]
    assert summary["registered_frames"] == summary["given_frames"] == len(NAMES) and summary["dropped"] == []
    assert summary["points"] == model.num_points3D() and summary["mean_reprojection_error_px"] < 1e-6
    assert summary["other_models"] == [] and "percentile" in summary["near_far_rule"]

    capture = read_transforms(tmp_path / "scene" / "transforms.json")  # the capture reader takes it
    np.testing.assert_allclose(capture.frames[0].c2w, truth[NAMES[0]]["c2w"], atol=1e-6)
    assert capture.frames[0].camera.distortion[:4] == pytest.approx(OPENCV_PARAMS[4:])
    # the sparse points, in the poses' world, for a per-scene Gaussian family to start from
    assert transforms["ply_file_path"] == "sparse_points.ply"
    xyz = read_sparse_points(capture, scale=1.0).xyz.numpy()
    expected_xyz = np.stack([point.xyz for point in model.points3D.values()])
    assert len(xyz) == model.num_points3D()
    np.testing.assert_allclose(np.sort(xyz, axis=0), np.sort(expected_xyz, axis=0), atol=1e-5)


@pytest.mark.parametrize(
    "model, params, expected",
    [
        ("SIMPLE_PINHOLE", [50.0, 32.0, 24.0], dict(camera_model="PINHOLE", fl_x=50.0, fl_y=50.0, cx=32.0, cy=24.0)),
        ("PINHOLE", [50.0, 51.0, 31.0, 23.0], dict(camera_model="PINHOLE", fl_x=50.0, fl_y=51.0, cx=31.0, cy=23.0)),
        ("SIMPLE_RADIAL", [50.0, 32.0, 24.0, -0.1],
         dict(camera_model="OPENCV", fl_x=50.0, fl_y=50.0, cx=32.0, cy=24.0, k1=-0.1, k2=0.0, p1=0.0, p2=0.0)),
        ("RADIAL", [50.0, 32.0, 24.0, -0.1, 0.02],
         dict(camera_model="OPENCV", fl_x=50.0, fl_y=50.0, cx=32.0, cy=24.0, k1=-0.1, k2=0.02, p1=0.0, p2=0.0)),
    ],
)
def test_exact_camera_models_become_pinhole_or_opencv(model, params, expected):
    assert camera_keys(make_camera(model, params)) == {**expected, "w": WIDTH, "h": HEIGHT}


def test_a_fisheye_model_is_undistorted_to_pinhole(tmp_path):
    width, height = 96, 72
    camera = make_camera("OPENCV_FISHEYE", [45.0, 45.0, 48.0, 36.0, 0.08, 0.02, 0.0, 0.0], width, height)
    model, _ = build_model(camera, ["a.jpg", "b.jpg"])
    sparse = write_model(model, tmp_path / "sparse", "bin")
    blobs = np.array([[20.3, 15.6], [70.2, 22.4], [48.0, 36.0], [30.5, 55.1], [80.4, 60.2]])  # distorted pixels
    rows, cols = np.mgrid[0:height, 0:width] + 0.5  # COLMAP: a pixel's centre is at +0.5
    image = sum(np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 1.2**2)) for u, v in blobs)
    (tmp_path / "images").mkdir()
    for name in ("a.jpg", "b.jpg"):
        Image.fromarray(np.repeat((255 * image.clip(0, 1)).astype(np.uint8)[..., None], 3, -1)).save(
            tmp_path / "images" / name, quality=100)

    transforms = import_colmap(sparse, tmp_path / "images", tmp_path / "scene")
    assert transforms["camera_model"] == "PINHOLE" and transforms["gpnerf_summary"]["undistorted"]
    assert [f["file_path"] for f in transforms["frames"]] == ["images/a.png", "images/b.png"]
    out = np.asarray(Image.open(tmp_path / "scene" / "images" / "a.png").convert("L"), dtype=np.float64)
    assert out.shape == (transforms["h"], transforms["w"])
    k = np.array([[transforms["fl_x"], 0, transforms["cx"]], [0, transforms["fl_y"], transforms["cy"]], [0, 0, 1]])
    rays = np.concatenate([camera.cam_from_img(blobs), np.ones((len(blobs), 1))], axis=1)
    expected = (rays @ k.T)[:, :2]
    for u, v in expected:
        r0, c0 = int(v), int(u)
        window = out[r0 - 4: r0 + 5, c0 - 4: c0 + 5]
        rr, cc = np.mgrid[r0 - 4: r0 + 5, c0 - 4: c0 + 5] + 0.5
        assert window.max() > 60, f"no blob near ({u:.1f}, {v:.1f})"
        centroid = np.array([(cc * window).sum(), (rr * window).sum()]) / window.sum()
        assert np.linalg.norm(centroid - [u, v]) < 0.3  # measured: at most 0.11 px


def test_the_largest_of_several_models_is_imported_and_the_others_reported(tmp_path, capsys):
    small, large = [f"a_{i}.png" for i in range(3)], [f"b_{i}.png" for i in range(5)]
    camera = make_camera("PINHOLE", [50.0, 50.0, 32.0, 24.0])
    write_model(build_model(camera, small)[0], tmp_path / "project" / "sparse" / "0", "txt")
    model, truth = build_model(camera, large, seed=1)
    write_model(model, tmp_path / "project" / "sparse" / "1", "bin")
    write_images(tmp_path / "images", small + large + ["never_registered.png"])
    for given in (tmp_path / "project" / "sparse", tmp_path / "project"):
        out = tmp_path / f"scene_{given.name}"
        assert cli_main(["data", "import-colmap", str(given), "--images", str(tmp_path / "images"),
                         "--out", str(out)]) == 0
        printed = capsys.readouterr().out
        transforms = json.loads((out / "transforms.json").read_text())
        summary = transforms["gpnerf_summary"]
        assert summary["model"] == str(tmp_path / "project" / "sparse" / "1")
        assert [o["registered_frames"] for o in summary["other_models"]] == [3]
        assert summary["registered_frames"] == 5 and summary["given_frames"] == 9
        reasons = {d["frame"]: d["reason"] for d in summary["dropped"]}
        assert set(reasons) == set(small) | {"never_registered.png"}
        assert all("smaller model" in reasons[name] for name in small)
        assert "not in the model" in reasons["never_registered.png"]
        assert sorted(p.name for p in (out / "images").iterdir()) == large
        np.testing.assert_allclose(transforms["frames"][2]["transform_matrix"], truth[large[2]]["c2w"] @ OPENGL,
                                   atol=1e-6)
        assert "registered 5 of 9 frames" in printed and "3 frames" in printed and "dropped 4" in printed


def test_a_registered_image_missing_from_images_is_dropped_with_its_reason(tmp_path):
    camera = make_camera("SIMPLE_PINHOLE", [50.0, 32.0, 24.0])
    sparse = write_model(build_model(camera, NAMES)[0], tmp_path / "sparse", "bin")
    write_images(tmp_path / "images", NAMES[1:])
    transforms = import_colmap(sparse, tmp_path / "images", tmp_path / "scene")
    missing = {"frame": NAMES[0], "reason": "image file missing from --images"}
    assert transforms["gpnerf_summary"]["dropped"] == [missing]
    assert len(transforms["frames"]) == 4 and transforms["camera_model"] == "PINHOLE"


def _one_line(code: int, err: str, *needles: str) -> None:
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("error: "), err
    for needle in needles:
        assert needle in err, err


@pytest.mark.parametrize("kind", ["bin", "txt"])
def test_an_unknown_camera_model_is_one_line_naming_file_and_value(tmp_path, capsys, kind):
    model, _ = build_model(make_camera("PINHOLE", [50.0, 50.0, 32.0, 24.0]), NAMES)
    sparse = write_model(model, tmp_path / "sparse", kind)
    write_images(tmp_path / "images", NAMES)
    if kind == "txt":
        text = (sparse / "cameras.txt").read_text().replace(" PINHOLE ", " WIDE_ANGLE ")
        (sparse / "cameras.txt").write_text(text)
        needles = ("cameras.txt", "'WIDE_ANGLE'")
    else:
        data = bytearray((sparse / "cameras.bin").read_bytes())
        struct.pack_into("<i", data, 12, 77)  # uint64 count, then int32 camera id, int32 model id
        (sparse / "cameras.bin").write_bytes(bytes(data))
        needles = ("cameras.bin", "model id 77")
    code, err = run_cli(capsys, sparse, "--images", tmp_path / "images", "--out", tmp_path / "scene")
    _one_line(code, err, *needles)
    assert not (tmp_path / "scene").exists() and not list(tmp_path.glob(".scene.partial-*"))


def test_refusals_leave_nothing_half_written(tmp_path, capsys):
    camera = make_camera("PINHOLE", [50.0, 50.0, 32.0, 24.0])
    sparse = write_model(build_model(camera, NAMES)[0], tmp_path / "sparse", "bin")
    write_images(tmp_path / "images", NAMES)
    images = tmp_path / "images"

    (tmp_path / "a_file").write_text("x")
    _one_line(*run_cli(capsys, sparse, "--images", images, "--out", tmp_path / "a_file" / "scene"), "a_file is a file")
    _one_line(*run_cli(capsys, sparse, "--images", images, "--out", images), "holds the input")
    _one_line(*run_cli(capsys, sparse, "--images", images, "--out", images / "scene"), "inside --images")
    _one_line(*run_cli(capsys, tmp_path / "nothing", "--images", images, "--out", tmp_path / "s"), "nothing: not found")
    _one_line(*run_cli(capsys, images, "--images", images, "--out", tmp_path / "s"), "no sparse model")

    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    _one_line(*run_cli(capsys, sparse, "--images", images, "--out", existing), "not empty", "--overwrite")
    assert (existing / "keep.txt").read_text() == "mine"

    Image.fromarray(np.zeros((HEIGHT + 2, WIDTH, 3), np.uint8)).save(images / NAMES[3])  # a different image
    _one_line(*run_cli(capsys, sparse, "--images", images, "--out", existing, "--overwrite"),
              NAMES[3], f"{WIDTH}x{HEIGHT + 2}", f"{WIDTH}x{HEIGHT}")
    assert (existing / "keep.txt").read_text() == "mine", "a failed --overwrite keeps the old scene"

    write_images(images, NAMES)
    assert run_cli(capsys, sparse, "--images", images, "--out", existing, "--overwrite")[0] == 0
    assert not (existing / "keep.txt").exists() and (existing / "transforms.json").is_file()
    assert not list(tmp_path.glob(".*.partial-*")), "temporary folders left behind"
    assert sorted(p.name for p in images.iterdir()) == NAMES, "the user's images are only read"


def test_an_interrupted_build_is_deleted_and_the_old_scene_kept(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with staged(out) as stage:
            (stage.scene / "transforms.json").write_text("{}")
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"] and (out / "old.txt").read_text() == "old"
    with staged(out) as stage:
        (stage.scene / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_no_registered_image_in_images_is_an_error(tmp_path):
    sparse = write_model(build_model(make_camera("PINHOLE", [50.0, 50.0, 32.0, 24.0]), NAMES)[0], tmp_path / "m", "bin")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="none of the 5 registered images"):
        import_colmap(sparse, tmp_path / "empty", tmp_path / "scene")
    assert not (tmp_path / "scene").exists()
