"""``files``: per-frame feature arrays a user wrote with their own model (CLIP, LSeg, DINO, SAM...), read by scene and
frame; optional text embeddings in the same channels make text queries possible. The layout (docs/features.md)::

    <root>/meta.json                    {"channels": C, "stride": s, "text_embeddings": "text.npz"}  (the last optional)
    <root>/<scene>/<frame>.npy          [C, h, w] float16 or float32, frame = the frame's index, 5 digits (00012.npy)
    <root>/text.npz                     one [C] array per text, keyed by the text (np.savez)

``h x w`` is the frame's size (the dataset's ``height x width``) over ``stride``, rounded (``FeatureProvider.
feature_size``). A missing frame, a wrong size or a wrong channel count is refused naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from gpnerf_core import ConfigError, DataError, FeatureProvider, from_launch_dir

META = "meta.json"


@dataclass
class FilesProviderConfig:
    name: str = "files"
    """Registry name and Hydra option (+feature_provider=files)."""
    root: str = ""
    """Folder of the layout: meta.json, <scene>/<frame>.npy (docs/features.md); relative to the launch directory."""


def frame_file(root: Path, scene: str, frame: int) -> Path:
    """Where frame ``frame`` of ``scene`` is: ``<root>/<scene>/<frame:05d>.npy``."""
    return root / scene / f"{int(frame):05d}.npy"


class FilesProvider(FeatureProvider):
    """The arrays of a ``files`` layout, checked against ``meta.json`` as they are read."""

    def __init__(self, *, root: str) -> None:
        if not root:
            raise ConfigError("feature_provider.root is empty; expected the folder of a files layout (meta.json and "
                              "<scene>/<frame>.npy, docs/features.md)")
        self.root = from_launch_dir(root)
        meta_path = self.root / META
        if not meta_path.is_file():
            raise ConfigError(f"{meta_path}: no such file; feature_provider.root={root} must hold meta.json "
                              '({"channels": C, "stride": s}) beside <scene>/<frame>.npy (docs/features.md)')
        try:
            meta = json.loads(meta_path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            raise DataError(f"{meta_path}: not JSON ({exc})") from None
        for key in ("channels", "stride"):
            value = meta.get(key) if isinstance(meta, dict) else None
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise DataError(f"{meta_path}: {key}={value!r}; expected a positive integer")
        self.channels, self.stride = int(meta["channels"]), int(meta["stride"])
        self.texts: dict[str, np.ndarray] = {}
        text_file = meta.get("text_embeddings")
        if text_file:
            self.texts = self._read_texts(self.root / str(text_file))
        self.text_encoder = bool(self.texts)
        self._fingerprint = "files|" + self._contents_hash(meta_path)

    def _read_texts(self, path: Path) -> dict[str, np.ndarray]:
        if not path.is_file():
            raise DataError(f"{path}: no such file; meta.json's text_embeddings names it (one [C] array per text, "
                            "np.savez(path, **{text: vector}))")
        try:
            with np.load(path, allow_pickle=False) as archive:
                texts = {text: np.asarray(archive[text]) for text in archive.files}
        except Exception as exc:
            raise DataError(f"{path}: not an .npz of text embeddings ({type(exc).__name__}: {exc})") from None
        for text, vector in texts.items():
            if vector.shape != (self.channels,) or not np.isfinite(vector).all():
                raise DataError(f"{path}: text {text!r} has an embedding of shape {list(vector.shape)}; expected "
                                f"[{self.channels}] finite values (meta.json's channels)")
        return texts

    def _contents_hash(self, meta_path: Path) -> str:
        """The root, meta.json and every .npy/.npz file's path, size and modification time: rewriting a frame gives
        another fingerprint, so the cache never serves the old features."""
        digest = hashlib.sha256(f"{self.root.resolve()}|".encode() + meta_path.read_bytes())
        for folder, dirs, names in sorted(os.walk(self.root)):
            dirs.sort()
            for name in sorted(names):
                if name.endswith((".npy", ".npz")):
                    stat = os.stat(os.path.join(folder, name))
                    digest.update(f"{os.path.relpath(os.path.join(folder, name), self.root)}|{stat.st_size}|"
                                  f"{stat.st_mtime_ns}\n".encode())
        return digest.hexdigest()[:24]

    def fingerprint(self) -> str:
        return self._fingerprint

    def compute(self, scene: str, frames: Sequence[int], images: Tensor) -> Tensor:
        cells = self.feature_size(int(images.shape[-2]), int(images.shape[-1]))
        expected = (self.channels, *cells)
        out = torch.empty(len(frames), *expected, dtype=torch.float32)
        for position, frame in enumerate(frames):
            path = frame_file(self.root, scene, frame)
            if not path.is_file():
                raise DataError(f"{path}: missing; the files layout needs one array per frame of scene {scene!r} "
                                f"({self.root}/<scene>/<frame:05d>.npy, [{self.channels}, {cells[0]}, {cells[1]}])")
            try:
                array = np.load(path, mmap_mode="r", allow_pickle=False)
            except Exception as exc:
                raise DataError(f"{path}: not a .npy array ({type(exc).__name__}: {exc})") from None
            if array.ndim != 3 or array.shape[0] != self.channels:
                raise DataError(f"{path}: shape {list(array.shape)}; expected {self.channels} channels, [C, h, w] "
                                f"= {list(expected)} (meta.json's channels)")
            if tuple(array.shape[1:]) != cells:
                raise DataError(f"{path}: size {array.shape[1]} x {array.shape[2]}; expected {cells[0]} x {cells[1]} "
                                f"(the frame's {images.shape[-2]} x {images.shape[-1]} over meta.json's stride "
                                f"{self.stride})")
            if array.dtype not in (np.float16, np.float32, np.float64):
                raise DataError(f"{path}: dtype {array.dtype}; expected float16 or float32")
            values = torch.from_numpy(np.asarray(array, dtype=np.float32))
            if not bool(torch.isfinite(values).all()):
                raise DataError(f"{path}: holds NaN or Inf")
            out[position] = values
        return out

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        if not self.texts:
            return super().encode_text(texts)
        unknown = [t for t in texts if t not in self.texts]
        if unknown:
            raise ConfigError(f"text {unknown[0]!r} has no embedding in the files layout {self.root}; known texts: "
                              f"{', '.join(sorted(self.texts))}")
        return torch.from_numpy(np.stack([self.texts[t] for t in texts]).astype(np.float32))
