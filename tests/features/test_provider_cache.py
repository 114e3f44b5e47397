"""The feature cache (``gpnerf_core.features``): filled once and read back without computing, keyed by the provider's
fingerprint, the scene and the frame size, memory-mapped and read shard by shard, and a corrupt shard or manifest
detected, said in one warning naming the file, deleted and computed again, never read."""

import json
import logging

import numpy as np
import pytest
import torch

from gpnerf_core import ConfigError, FeatureCache, frame_features
from gpnerf_core.features import cache as cache_module
from features.provider_scenes import CountingProvider, TinyScenes


@pytest.fixture
def small_shards(monkeypatch):
    """Shards of 4 frames (6 channels x 12 x 16 cells x 2 bytes = 2304 bytes per frame)."""
    monkeypatch.setattr(cache_module, "SHARD_BYTES", 4 * 6 * 12 * 16 * 2)


def expected(provider, dataset, frames):
    scene = dataset.load_scene("s0")
    images = torch.stack([scene.load_frame(f).rgb.permute(2, 0, 1) for f in frames])
    return CountingProvider(provider.scale).compute("s0", frames, images)


def test_filled_once_then_read_without_computing(tmp_path, small_shards):
    provider, dataset = CountingProvider(), TinyScenes(frames=10)
    first = FeatureCache(provider, dataset, "s0", root=tmp_path)
    assert first.shard_frames == 4 and first.num_shards == 3
    features = first.features([7, 1, 9])
    assert features.shape == (3, 6, 12, 16) and features.dtype == torch.float32
    assert sorted(provider.frames) == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]  # the three shards the frames fall in
    assert torch.allclose(features, expected(provider, dataset, [7, 1, 9]), atol=2e-3)
    provider.frames.clear()
    second = FeatureCache(provider, dataset, "s0", root=tmp_path)
    again = second.features([9, 1, 7, 7])
    assert provider.frames == [] and second.computed == 0 and second.read == 4
    assert torch.equal(again[[2, 1, 0]], features)
    manifest = json.loads((first.folder / "manifest.json").read_text())
    assert sorted(manifest["shards"]) == ["0", "1", "2"] and len(manifest["shards"]["2"]["checksums"]) == 2
    assert manifest["dtype"] == "float16" and manifest["channels"] == 6


def test_only_the_shards_asked_for_are_computed_and_mapped(tmp_path, small_shards):
    provider, dataset = CountingProvider(), TinyScenes(frames=10)
    cache = FeatureCache(provider, dataset, "s0", root=tmp_path)
    cache.features([5])
    assert provider.frames == [4, 5, 6, 7] and cache.missing_shards() == [0, 2]
    assert all(isinstance(array, np.memmap) for array in cache._open.values())
    cache.features([0, 9])
    assert len(cache._open) <= cache_module.OPEN_SHARDS
    assert cache.fill() == 0 and sorted(provider.frames) == list(range(10))


def test_a_changed_config_scene_or_size_is_another_folder(tmp_path):
    dataset = TinyScenes(frames=3)
    folders = {FeatureCache(CountingProvider(), dataset, "s0", root=tmp_path).folder,
               FeatureCache(CountingProvider(scale=2.0), dataset, "s0", root=tmp_path).folder,
               FeatureCache(CountingProvider(), TinyScenes(frames=3, seed=1), "s0", root=tmp_path).folder,
               FeatureCache(CountingProvider(), TinyScenes(frames=3, height=64, width=96), "s0", root=tmp_path).folder,
               FeatureCache(CountingProvider(), TinyScenes(frames=4), "s0", root=tmp_path).folder}
    assert len(folders) == 5
    scaled = CountingProvider(scale=2.0)
    assert torch.allclose(frame_features(scaled, dataset, "s0", [1], root=tmp_path),
                          2 * frame_features(CountingProvider(), dataset, "s0", [1], root=tmp_path), atol=4e-3)


def test_the_default_folder_is_under_gpnerf_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "c"))
    provider, dataset = CountingProvider(), TinyScenes(frames=2)
    frame_features(provider, dataset, "s0", [0, 1])
    frame_features(provider, dataset, "s0", [1])  # the opened cache is kept: nothing computed again
    assert provider.frames == [0, 1]
    assert [p.parent.name for p in (tmp_path / "c" / "features").glob("*/manifest.json")] != []


def corrupt(path, how):
    data = bytearray(path.read_bytes())
    if how == "flip":
        data[-7] ^= 0xFF  # inside the last frame's values
    elif how == "truncate":
        data = data[: len(data) // 2]
    elif how == "header":
        data[:6] = b"NOTNPY"
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["flip", "truncate", "header"])
def test_a_corrupt_shard_is_said_deleted_and_computed_again(tmp_path, small_shards, caplog, how):
    provider, dataset = CountingProvider(), TinyScenes(frames=8)
    good = FeatureCache(provider, dataset, "s0", root=tmp_path).features(range(8))
    shard = tmp_path / FeatureCache(provider, dataset, "s0", root=tmp_path).key / "shard_00001.npy"
    corrupt(shard, how)
    provider.frames.clear()
    cache = FeatureCache(provider, dataset, "s0", root=tmp_path)
    with caplog.at_level(logging.WARNING, logger="gpnerf_core.features.cache"):
        assert torch.equal(cache.features([2, 3]), good[[2, 3]])  # shard 0: untouched, nothing said
        assert caplog.records == [] and provider.frames == []
        again = cache.features([7, 4])
    assert torch.equal(again, good[[7, 4]])
    assert provider.frames == [4, 5, 6, 7]
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and str(shard) in lines[0] and "\n" not in lines[0]
    assert shard.is_file()  # written again, and reads back clean
    provider.frames.clear()
    assert torch.equal(FeatureCache(provider, dataset, "s0", root=tmp_path).features([4, 7]), good[[4, 7]])
    assert provider.frames == []


def test_a_corrupt_manifest_is_replaced(tmp_path, caplog):
    provider, dataset = CountingProvider(), TinyScenes(frames=3)
    cache = FeatureCache(provider, dataset, "s0", root=tmp_path)
    good = cache.features([0, 1, 2])
    (cache.folder / "manifest.json").write_text('{"format": 1, "shards": ')
    provider.frames.clear()
    with caplog.at_level(logging.WARNING, logger="gpnerf_core.features.cache"):
        assert torch.equal(FeatureCache(provider, dataset, "s0", root=tmp_path).features([2]), good[[2]])
    assert provider.frames == [0, 1, 2]
    assert any("manifest.json" in r.getMessage() for r in caplog.records)


def test_float16_storage_error_on_unit_descriptors(tmp_path):
    """The cache stores float16: on unit-length descriptors the error against float32 stays below 5e-4."""

    class Unit(CountingProvider):
        channels = 64

        def compute(self, scene, frames, images):
            g = torch.Generator().manual_seed(len(frames))
            x = torch.randn(len(frames), 64, 12, 16, generator=g)
            return torch.nn.functional.normalize(x, dim=1)

    provider = Unit()
    stored = FeatureCache(provider, TinyScenes(frames=2), "s0", root=tmp_path).features([0, 1])
    exact = provider.compute("s0", [0, 1], None)
    error = float((stored - exact).abs().max())
    assert 0 < error < 5e-4


def test_bad_frames_and_bad_provider_output_are_refused(tmp_path):
    provider, dataset = CountingProvider(), TinyScenes(frames=3)
    with pytest.raises(ConfigError, match=r"frame 3 of scene 's0': expected an index in \[0, 3\)"):
        FeatureCache(provider, dataset, "s0", root=tmp_path).features([3])

    class Wrong(CountingProvider):
        def compute(self, scene, frames, images):
            return super().compute(scene, frames, images)[:, :5]

    with pytest.raises(Exception, match=r"returned \[3, 5, 12, 16\], expected \[3, 6, 12, 16\]"):
        FeatureCache(Wrong(), dataset, "s0", root=tmp_path).features([0])

    class Huge(CountingProvider):
        def fingerprint(self):
            return "huge"

        def compute(self, scene, frames, images):
            return super().compute(scene, frames, images) + 1e6

    with pytest.raises(Exception, match="beyond float16"):
        FeatureCache(Huge(), dataset, "s0", root=tmp_path).features([0])


def test_two_caches_filling_one_folder_keep_each_others_shards(tmp_path, small_shards):
    """Each manifest update re-reads the manifest under the folder's lock: a reader that opened it before another
    filled a shard neither loses that shard nor computes it again."""
    dataset = TinyScenes(frames=8)
    one, two = CountingProvider(), CountingProvider()
    first, second = (FeatureCache(p, dataset, "s0", root=tmp_path) for p in (one, two))
    assert first.missing_shards() == second.missing_shards() == [0, 1]
    first.features([0])
    second.features([5])
    assert one.frames == [0, 1, 2, 3] and two.frames == [4, 5, 6, 7]
    assert second.features([1]).shape == (1, 6, 12, 16) and two.frames == [4, 5, 6, 7]
    assert sorted(json.loads((first.folder / "manifest.json").read_text())["shards"]) == ["0", "1"]


def test_a_shard_rewritten_by_another_process_is_read_again_not_deleted(tmp_path, small_shards, caplog):
    """A reader whose manifest predates another process's rewrite of a shard (other bytes, other checksums) reads the
    new file against the new checksums: nothing is said, deleted or computed."""
    dataset = TinyScenes(frames=4)
    reader = FeatureCache(CountingProvider(), dataset, "s0", root=tmp_path)
    reader.features([0])
    writer_provider = CountingProvider()
    writer = FeatureCache(writer_provider, dataset, "s0", root=tmp_path)
    writer._computed = lambda frames: np.full((len(frames), 6, 12, 16), 0.5, np.float16)  # other bytes
    writer.fill_shard(0)
    reader._open.clear()  # as after its two mapped shards were closed
    with caplog.at_level(logging.WARNING, logger="gpnerf_core.features.cache"):
        assert float(reader.features([1]).mean()) == 0.5
    assert caplog.records == [] and reader.computed == 1 * 4
