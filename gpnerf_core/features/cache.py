"""The on-disk cache of a feature provider's per-frame features: memory-mapped shards keyed by a hash.

One folder per (provider fingerprint, scene identity, frame size), ``$GPNERF_CACHE/features/<key>/`` (default
``~/.cache/gpnerf``)::

    manifest.json        what the folder holds and one checksum per frame of every shard written
    shard_00000.npy      frames [0, S) of the scene: [S, C, h, w] float16 (numpy's .npy format)
    shard_00001.npy      frames [S, 2S) ... the last shard holds the rest
    .lock                serialises manifest updates between processes

A shard is computed whole, ``batch`` frames at a time, then written atomically (temporary file, ``os.replace``) and
recorded in the manifest (rewritten atomically) together under the folder's lock, so two runs filling the same folder
never lose each other's shards nor pair one's file with the other's checksums. Reading opens a shard with numpy's memory mapping and copies out only the frames asked
for, each checked against its CRC-32 first: a run holds one shard being filled, or the frames it asked for, never every
frame's features. At most ``OPEN_SHARDS`` shards stay mapped.

Features are stored as float16 (half the disk and page cache of float32): for unit-length descriptors (XFeat's) the
largest error is 2^-11 of a value, below 5e-4 (``tests/features/test_feature_cache.py`` measures it); a provider whose
values leave float16's range (|x| > 65504) is refused naming it, never stored as Inf.

A shard that is truncated, whose header does not parse, whose shape differs from the manifest's or whose frame fails
its checksum is said in one warning line naming the file, deleted (only our own ``shard_*.npy``) and computed again,
never read. A manifest that does not parse or describes another folder's contents is replaced the same way.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import zlib
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor

from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.errors import ConfigError, DataError, PluginError
from gpnerf_core.interfaces.feature_provider import FeatureProvider
from gpnerf_core.runtime.io import atomic_open, atomic_write_json
from gpnerf_core.types import Scene

log = logging.getLogger(__name__)

CACHE_ENV = "GPNERF_CACHE"
FORMAT = 1
"""Version of the folder layout and manifest; part of the key, so a new layout never reads an old one."""
STORED_DTYPE = np.float16
FLOAT16_MAX = float(np.finfo(np.float16).max)
SHARD_BYTES = 32 * 2**20
"""Target size of a shard: ``shard_frames`` = this over one frame's bytes, between 1 and ``MAX_SHARD_FRAMES``."""
MAX_SHARD_FRAMES = 64
OPEN_SHARDS = 2
"""Shards kept memory-mapped at once (least recently used closed first): a run's resident memory stays flat however
many frames it reads."""
MANIFEST = "manifest.json"


def cache_root() -> Path:
    """``$GPNERF_CACHE/features`` (default ``~/.cache/gpnerf/features``)."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "gpnerf").expanduser() / "features"


def scene_identity(dataset: SceneDataset, scene: Scene) -> str:
    """A hash of what a scene's frames are: the dataset's class, the scene's name, frame size and count, every camera
    (poses and intrinsics) and the first frame's pixels. Another seed, texture or size of a generated set, or other
    files under the same scene name, give another identity (and so another cache folder)."""
    digest = hashlib.sha256()
    kind = type(dataset)
    digest.update(f"{kind.__module__}.{kind.__qualname__}|{scene.name}|{scene.height}x{scene.width}|"
                  f"{scene.num_frames}".encode())
    for tensor in (scene.c2w, scene.intrinsics):
        digest.update(np.ascontiguousarray(tensor.detach().cpu().float().numpy()).tobytes())
    if scene.num_frames:
        digest.update(np.ascontiguousarray(scene.load_frame(0).rgb.detach().cpu().float().numpy()).tobytes())
    return digest.hexdigest()


def cache_key(fingerprint: str, identity: str, height: int, width: int, shard_frames: int) -> str:
    """The folder name of one (provider fingerprint, scene identity, frame size) in one layout (``FORMAT``, frames per
    shard): 24 hex digits of a SHA-256."""
    text = json.dumps({"format": FORMAT, "provider": fingerprint, "scene": identity, "size": [height, width],
                       "shard_frames": shard_frames}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def frame_checksum(frame: np.ndarray) -> str:
    """CRC-32 of one stored frame's bytes, 8 hex digits."""
    return f"{zlib.crc32(np.ascontiguousarray(frame).tobytes()) & 0xFFFFFFFF:08x}"


class CorruptShard(Exception):
    """A shard that must not be read (internal: caught, warned about and recomputed)."""


class FeatureCache:
    """One provider's features of one scene's frames, read from and filled into its cache folder.

    Args:
        provider: the feature provider.
        dataset: the dataset the scene belongs to (its frames are the provider's images).
        scene: the scene, or its name in ``dataset``.
        root: the cache's base folder (default ``cache_root()``).
        batch: frames per ``provider.compute`` call while a shard fills.
        device: where the images go for ``compute`` (default CPU).

    Attributes:
        computed: frames computed by this object so far (``provider.compute`` calls' frames).
        read: frames read from disk so far.
    """

    def __init__(self, provider: FeatureProvider, dataset: SceneDataset, scene: Scene | str, *,
                 root: Path | str | None = None, batch: int = 8, device: torch.device | str | None = None) -> None:
        if batch < 1:
            raise ConfigError(f"feature cache batch={batch}: expected at least 1 frame per compute call")
        self.provider = provider
        self.dataset = dataset
        self.scene = dataset.load_scene(scene) if isinstance(scene, str) else scene
        self.batch = int(batch)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        channels, stride = getattr(provider, "channels", None), getattr(provider, "stride", None)
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in (channels, stride)):
            raise PluginError(f"feature provider {self.name}: channels={channels!r}, stride={stride!r}; expected "
                              "positive integers (FeatureProvider's attributes)")
        self.channels = int(channels)
        self.size = provider.feature_size(self.scene.height, self.scene.width)
        frame_bytes = self.channels * self.size[0] * self.size[1] * np.dtype(STORED_DTYPE).itemsize
        self.shard_frames = int(min(MAX_SHARD_FRAMES, max(1, SHARD_BYTES // frame_bytes)))
        self.fingerprint = str(provider.fingerprint())
        self.identity = scene_identity(dataset, self.scene)
        self.key = cache_key(self.fingerprint, self.identity, self.scene.height, self.scene.width, self.shard_frames)
        self.folder = Path(root).expanduser() if root is not None else cache_root()
        self.folder = self.folder / self.key
        self.computed = 0
        self.read = 0
        self._open: OrderedDict[int, np.ndarray] = OrderedDict()
        self._manifest: dict[str, Any] | None = None

    @property
    def name(self) -> str:
        return type(self.provider).__name__

    @property
    def num_frames(self) -> int:
        return self.scene.num_frames

    @property
    def num_shards(self) -> int:
        return -(-self.num_frames // self.shard_frames)

    def shard_path(self, shard: int) -> Path:
        return self.folder / f"shard_{shard:05d}.npy"

    def shard_range(self, shard: int) -> range:
        return range(shard * self.shard_frames, min(self.num_frames, (shard + 1) * self.shard_frames))

    def description(self) -> dict[str, Any]:
        """What the manifest says about the folder besides its shards; a manifest that differs is not ours."""
        return {"format": FORMAT, "key": self.key, "provider": self.fingerprint, "scene": self.scene.name,
                "scene_identity": self.identity, "frames": self.num_frames, "height": self.scene.height,
                "width": self.scene.width, "channels": self.channels, "feature_height": self.size[0],
                "feature_width": self.size[1], "dtype": np.dtype(STORED_DTYPE).name,
                "shard_frames": self.shard_frames}

    # ---- reading

    def features(self, frames: Sequence[int]) -> Tensor:
        """``[n, C, h, w]`` float32 features of ``frames`` (indices into the scene, in the order given), read from
        their shards (each computed first if missing or corrupt)."""
        frames = [int(f) for f in frames]
        bad = [f for f in frames if not 0 <= f < self.num_frames]
        if bad:
            raise ConfigError(f"frame {bad[0]} of scene {self.scene.name!r}: expected an index in [0, "
                              f"{self.num_frames})")
        out = torch.empty(len(frames), self.channels, *self.size, dtype=torch.float32)
        by_shard: dict[int, list[int]] = {}
        for position, frame in enumerate(frames):
            by_shard.setdefault(frame // self.shard_frames, []).append(position)
        for shard, positions in sorted(by_shard.items()):
            for attempt in (0, 1):
                try:
                    self._read_into(out, shard, positions, frames)
                    break
                except CorruptShard as exc:
                    if attempt:
                        raise DataError(f"{self.shard_path(shard)}: corrupt again right after it was written ({exc}); "
                                        f"the cache folder {self.folder} is not usable") from None
                    self._discard(shard, str(exc))
        return out

    def _read_into(self, out: Tensor, shard: int, positions: list[int], frames: list[int]) -> None:
        array = self._shard(shard)
        sums = self._manifest_now()["shards"][str(shard)]["checksums"]
        start = shard * self.shard_frames
        for position in positions:
            row = frames[position] - start
            frame = np.asarray(array[row])
            if frame_checksum(frame) != sums[row]:
                raise CorruptShard(f"frame {frames[position]} fails its checksum")
            out[position] = torch.from_numpy(frame.astype(np.float32))
        self.read += len(positions)  # counted once the shard's frames all passed

    def _shard(self, shard: int) -> np.ndarray:
        """Shard ``shard`` memory-mapped (filled first when the manifest has none or its file is missing)."""
        if shard in self._open:
            self._open.move_to_end(shard)
            return self._open[shard]
        entry = self._manifest_now()["shards"].get(str(shard))
        path = self.shard_path(shard)
        if entry is None or not path.is_file():
            self._manifest = None  # another process may have filled it since the manifest was read
            entry = self._manifest_now()["shards"].get(str(shard))
        if entry is None or not path.is_file():
            self.fill_shard(shard)
            entry = self._manifest_now()["shards"][str(shard)]
        size = path.stat().st_size
        if size != entry.get("bytes"):
            raise CorruptShard(f"{size} bytes, the manifest says {entry.get('bytes')} (truncated or overwritten)")
        try:
            array = np.load(path, mmap_mode="r", allow_pickle=False)
        except Exception as exc:  # a header numpy cannot parse, a file shorter than its header says
            raise CorruptShard(f"unreadable .npy: {type(exc).__name__}: {exc}") from None
        expected = (len(self.shard_range(shard)), self.channels, *self.size)
        if tuple(array.shape) != expected or array.dtype != STORED_DTYPE:
            raise CorruptShard(f"holds {array.dtype} {list(array.shape)}, expected {np.dtype(STORED_DTYPE).name} "
                               f"{list(expected)}")
        if len(entry.get("checksums", ())) != expected[0]:
            raise CorruptShard(f"the manifest has {len(entry.get('checksums', ()))} checksums for {expected[0]} frames")
        self._open[shard] = array
        while len(self._open) > OPEN_SHARDS:
            self._open.popitem(last=False)
        return array

    def _discard(self, shard: int, why: str) -> None:
        """Shard ``shard`` was found corrupt: say so in one line naming its file, forget it and delete the file; unless
        another process rewrote it (and its manifest entry) since this one read them, then only read it again."""
        path = self.shard_path(shard)
        judged = (self._manifest or {}).get("shards", {}).get(str(shard))
        self._open.pop(shard, None)
        with self._locked():
            manifest = self._load_manifest()
            self._manifest = manifest
            if manifest["shards"].get(str(shard)) != judged:
                return  # rewritten meanwhile: the next read checks the new file against its new checksums
            log.warning("corrupt feature cache shard %s (%s): deleted, computing it again", path, why)
            manifest["shards"].pop(str(shard), None)
            atomic_write_json(self.folder / MANIFEST, manifest)
            with contextlib.suppress(FileNotFoundError):
                path.unlink()

    # ---- filling

    def missing_shards(self) -> list[int]:
        """Shards the manifest does not record or whose file is gone (not checked for corruption: reading does)."""
        self._manifest = None
        shards = self._manifest_now()["shards"]
        return [s for s in range(self.num_shards) if str(s) not in shards or not self.shard_path(s).is_file()]

    def fill(self, progress: Callable[[int], None] | None = None) -> int:
        """Compute every missing shard; ``progress(frames)`` after each batch. Returns the frames computed."""
        before = self.computed
        for shard in self.missing_shards():
            self.fill_shard(shard, progress)
        return self.computed - before

    def fill_shard(self, shard: int, progress: Callable[[int], None] | None = None) -> None:
        """Compute shard ``shard``'s frames ``batch`` at a time into one float16 array, write it atomically and record
        its checksums in the manifest."""
        frames = list(self.shard_range(shard))
        array = np.empty((len(frames), self.channels, *self.size), dtype=STORED_DTYPE)
        for start in range(0, len(frames), self.batch):
            chunk = frames[start:start + self.batch]
            array[start:start + len(chunk)] = self._computed(chunk)
            self.computed += len(chunk)
            if progress is not None:
                progress(len(chunk))
        path = self.shard_path(shard)
        checksums = [frame_checksum(frame) for frame in array]
        with self._locked():  # the file and its manifest entry change together: another process sees both or neither
            manifest = self._load_manifest()
            with atomic_open(path, "wb") as handle:
                np.save(handle, array, allow_pickle=False)
            manifest["shards"][str(shard)] = {"file": path.name, "bytes": path.stat().st_size,
                                              "frames": [frames[0], frames[-1] + 1], "checksums": checksums}
            atomic_write_json(self.folder / MANIFEST, manifest)
            self._manifest = manifest
        self._open.pop(shard, None)

    def _computed(self, frames: list[int]) -> np.ndarray:
        """``provider.compute`` of ``frames``, checked and converted to the stored dtype."""
        images = torch.stack([self.scene.load_frame(f).rgb.permute(2, 0, 1) for f in frames]).float().to(self.device)
        module = isinstance(self.provider, torch.nn.Module)
        if module:
            self.provider.eval()
        with torch.no_grad():
            out = self.provider.compute(self.scene.name, frames, images)
        expected = [len(frames), self.channels, *self.size]
        if not isinstance(out, Tensor) or list(out.shape) != expected:
            got = list(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise PluginError(f"feature provider {self.name}.compute(scene {self.scene.name!r}, frames "
                              f"{frames[0]}..{frames[-1]}) returned {got}, expected {expected} (channels, frame "
                              f"{self.scene.height}x{self.scene.width} over stride {self.provider.stride})")
        out = out.detach().float().cpu()
        if not bool(torch.isfinite(out).all()):
            raise PluginError(f"feature provider {self.name} gave NaN or Inf features for scene "
                              f"{self.scene.name!r}, frames {frames[0]}..{frames[-1]}")
        peak = float(out.abs().max()) if out.numel() else 0.0
        if peak > FLOAT16_MAX:
            raise DataError(f"feature provider {self.name}: features of scene {self.scene.name!r}, frames "
                            f"{frames[0]}..{frames[-1]} reach |x| = {peak:.3g}, beyond float16's {FLOAT16_MAX:g} "
                            "the cache stores; scale them down (normalise them) before giving them")
        return out.numpy().astype(STORED_DTYPE)

    # ---- the manifest

    def _manifest_now(self) -> dict[str, Any]:
        if self._manifest is None:
            with self._locked():
                self._manifest = self._load_manifest()
        return self._manifest

    def _load_manifest(self) -> dict[str, Any]:
        """The manifest on disk (call under the lock); a fresh one when there is none, and one that does not parse or
        describes another folder is replaced (its shards deleted) with a warning naming it."""
        path = self.folder / MANIFEST
        fresh = {**self.description(), "shards": {}}
        if not path.is_file():
            return fresh
        try:
            manifest = json.loads(path.read_text())
            ours = isinstance(manifest, dict) and isinstance(manifest.get("shards"), dict) and all(
                manifest.get(k) == v for k, v in self.description().items())
            why = "it describes other contents" if not ours else ""
        except (ValueError, UnicodeDecodeError) as exc:
            ours, why = False, f"it does not parse: {exc}"
        if ours:
            return manifest
        log.warning("corrupt feature cache manifest %s (%s): its shards are deleted and computed again", path, why)
        for shard in self.folder.glob("shard_*.npy"):
            shard.unlink()
        self._open.clear()
        atomic_write_json(path, fresh)
        return fresh

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """An exclusive lock on the folder's ``.lock`` (POSIX ``flock``; without it, on other systems, none)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            import fcntl
        except ImportError:  # not POSIX: writes stay atomic, concurrent fills may redo a shard
            yield
            return
        with open(self.folder / ".lock", "a") as handle:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def frame_features(provider: FeatureProvider, dataset: SceneDataset, scene: Scene | str, frames: Sequence[int], *,
                   root: Path | str | None = None, device: torch.device | str | None = None) -> Tensor:
    """The features of ``frames`` of ``scene``, ``[n, C, h, w]`` float32 on the CPU, read through the on-disk cache
    (``$GPNERF_CACHE/features/<key>/``): computed by ``provider`` at first use (the whole shards they fall in),
    read back from memory-mapped shards afterwards.

    Args:
        provider: the feature provider (``build_feature_provider(cfg)`` builds a run's).
        dataset: the dataset whose scene it is; its frames are the provider's images, at the size it loads them.
        scene: the scene or its name.
        frames: frame indices in the scene.
        root: the cache's base folder (default ``$GPNERF_CACHE/features``).
        device: where ``provider.compute`` runs (default CPU).
    """
    return opened_cache(provider, dataset, scene, root=root, device=device).features(frames)


_OPENED: OrderedDict[tuple[int, int, str, str], tuple[Any, Any, FeatureCache]] = OrderedDict()
"""Caches ``frame_features`` opened, by (provider, dataset, scene, root); each with the provider and dataset objects
themselves (so an id is never reused for another while its entry lives)."""


def opened_cache(provider: FeatureProvider, dataset: SceneDataset, scene: Scene | str, *,
                 root: Path | str | None = None, device: torch.device | str | None = None) -> FeatureCache:
    """The ``FeatureCache`` of (provider, dataset, scene), opened once and kept (the last 8): repeated
    ``frame_features`` calls hash the scene and read the manifest once."""
    name = scene if isinstance(scene, str) else scene.name
    key = (id(provider), id(dataset), name, str(root if root is not None else cache_root()))
    entry = _OPENED.get(key)
    if entry is not None and entry[0] is provider and entry[1] is dataset:
        _OPENED.move_to_end(key)
        return entry[2]
    cache = FeatureCache(provider, dataset, scene, root=root, device=device)
    _OPENED[key] = (provider, dataset, cache)
    while len(_OPENED) > 8:
        _OPENED.popitem(last=False)
    return cache
