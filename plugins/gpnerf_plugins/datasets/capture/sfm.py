"""Structure from motion through pycolmap: SIFT features, sequential or exhaustive matching, incremental mapping.

- Features: one camera for all frames (``CameraMode.SINGLE``) of ``SfmOptions.camera_model``, its parameters refined
  by bundle adjustment; or, with ``SfmOptions.intrinsics``, a PINHOLE camera with those parameters held fixed.
- Matching: ``sequential`` (each frame against its neighbours in name order: videos) or ``exhaustive`` (every pair:
  small photo sets).
- Mapping: ``incremental_mapping``; it may split the frames into several models (the import takes the largest).

Each pycolmap call runs in a worker thread (pycolmap releases the GIL) with a ``CancellationToken``: Ctrl-C cancels
the call and raises ``KeyboardInterrupt`` here at once instead of after the stage. COLMAP's log is kept to errors
unless ``SfmOptions.verbose``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from tqdm import tqdm

from gpnerf_core import ConfigError, DataError
from gpnerf_plugins.datasets.capture.colmap_import import load_pycolmap
from gpnerf_plugins.datasets.common.image_io import one_line_error

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""Camera models structure from motion may fit; all are written to the capture exactly (PINHOLE or OPENCV)."""
MATCHERS = ("sequential", "exhaustive")
DEVICES = ("auto", "cpu", "cuda")
FEATURE_BATCH = 10
"""Frames per feature-extraction call (the progress bar's step)."""
MIN_MODEL_SIZE = 3
"""Smallest model the mapper keeps (COLMAP's default, 10, would hide a small capture's partial model)."""


@dataclass(frozen=True)
class SfmOptions:
    """How to run structure from motion.

    Attributes:
        camera_model: one of ``CAMERA_MODELS`` (ignored with ``intrinsics``).
        intrinsics: ``(fx, fy, cx, cy)`` in pixels of the frames handed to SfM (COLMAP convention: the top-left pixel's
            centre at 0.5, 0.5), held fixed; None lets SfM estimate the camera.
        matcher: one of ``MATCHERS``.
        device: ``auto`` (CUDA where pycolmap was built with it), ``cpu`` or ``cuda``.
        threads: CPU threads per stage (-1: all cores).
        seed: pycolmap's random seed (RANSAC, mapper).
        verbose: show COLMAP's own log.
    """

    camera_model: str = "SIMPLE_PINHOLE"
    intrinsics: tuple[float, float, float, float] | None = None
    matcher: str = "sequential"
    device: str = "auto"
    threads: int = -1
    seed: int = 0
    verbose: bool = False


@dataclass
class SfmResult:
    """``sparse``: the folder holding the models (``0/``, ``1/``, ...); ``registered``: registered frames per model
    folder name; ``seconds``: per stage (``features``, ``matching``, ``mapping``)."""

    sparse: Path
    registered: dict[str, int]
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def best(self) -> int:
        """Registered frames of the largest model (0 when the mapper made none)."""
        return max(self.registered.values(), default=0)


def _device(pycolmap: Any, device: str) -> Any:
    if device not in DEVICES:
        raise ConfigError(f"--device {device}; expected one of {', '.join(DEVICES)}")
    if device == "cuda" and not pycolmap.has_cuda:
        raise ConfigError(
            f"--device cuda: this pycolmap {pycolmap.__version__} has no CUDA; expected --device cpu or auto"
        )
    return getattr(pycolmap.Device, device)


def _cancellable(pycolmap: Any, bar: tqdm, function: Callable[..., Any], stage: str, **kwargs: Any) -> Any:
    """``function(**kwargs)`` in a worker thread, the bar refreshed meanwhile; Ctrl-C cancels it."""
    token = pycolmap.CancellationToken()
    outcome: dict[str, Any] = {}

    def work() -> None:
        try:
            outcome["value"] = function(**kwargs, cancellation_token=token)
        except BaseException as exc:  # handed to the main thread
            outcome["error"] = exc

    thread = threading.Thread(target=work, name=f"pycolmap-{stage}", daemon=True)
    try:
        thread.start()  # inside the try: Ctrl-C can land while start() waits for the thread
        while thread.is_alive():
            thread.join(0.2)
            bar.refresh()
    except BaseException:
        token.cancel()
        if thread.ident is not None:
            thread.join()  # the caller deletes the folders this call writes into
        raise
    if "error" in outcome:
        raise DataError(f"structure from motion failed in {stage} ({one_line_error(outcome['error'])})") from None
    return outcome.get("value")


def run_sfm(images: Path, names: list[str], work: Path, options: SfmOptions, progress: bool | None = None) -> SfmResult:
    """Run SfM on ``images/<names>`` with its database and models under ``work``; models go to ``work/sparse``.

    Raises:
        ConfigError: an unknown camera model, matcher or device, or CUDA asked of a CPU build.
        DataError: a pycolmap stage failed (its message on one line).
    """
    pycolmap = load_pycolmap()
    if options.intrinsics is None and options.camera_model not in CAMERA_MODELS:
        raise ConfigError(f"--camera-model {options.camera_model}; expected one of {', '.join(CAMERA_MODELS)}")
    if options.matcher not in MATCHERS:
        raise ConfigError(f"--matcher {options.matcher}; expected one of {', '.join(MATCHERS)}")
    device = _device(pycolmap, options.device)
    database, sparse = work / "database.db", work / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    disable = None if progress is None else not progress
    result = SfmResult(sparse, {})
    log_level = pycolmap.logging.minloglevel
    if not options.verbose:
        pycolmap.logging.minloglevel = 2  # errors only
    pycolmap.set_random_seed(options.seed)
    try:
        reader = pycolmap.ImageReaderOptions()
        if options.intrinsics is not None:
            reader.camera_model = "PINHOLE"
            reader.camera_params = ",".join(repr(float(v)) for v in options.intrinsics)
        else:
            reader.camera_model = options.camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = options.threads
        start = time.perf_counter()
        with tqdm(total=len(names), desc="features", unit="frame", disable=disable) as bar:
            for first in range(0, len(names), FEATURE_BATCH):
                batch = names[first: first + FEATURE_BATCH]
                _cancellable(pycolmap, bar, pycolmap.extract_features, "feature extraction", database_path=database,
                             image_path=images, image_names=batch, camera_mode=pycolmap.CameraMode.SINGLE,
                             reader_options=reader, extraction_options=extraction, device=device)
                reader.existing_camera_id = 1  # later batches share the first batch's camera
                bar.update(len(batch))
        result.seconds["features"] = time.perf_counter() - start

        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = options.threads
        match = pycolmap.match_sequential if options.matcher == "sequential" else pycolmap.match_exhaustive
        start = time.perf_counter()
        with tqdm(total=1, desc=f"matching ({options.matcher})", unit="stage", disable=disable) as bar:
            _cancellable(pycolmap, bar, match, "matching", database_path=database, matching_options=matching,
                         device=device)
            bar.update(1)
        result.seconds["matching"] = time.perf_counter() - start

        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = options.threads
        mapping.random_seed = options.seed
        mapping.min_model_size = MIN_MODEL_SIZE
        if options.intrinsics is not None:
            mapping.ba_refine_focal_length = False
            mapping.ba_refine_principal_point = False
            mapping.ba_refine_extra_params = False
        start = time.perf_counter()
        with tqdm(desc="mapping", unit="image tried", disable=disable) as bar:
            models = _cancellable(pycolmap, bar, pycolmap.incremental_mapping, "mapping", database_path=database,
                                  image_path=images, output_path=sparse, options=mapping,
                                  next_image_callback=lambda: bar.update(1))
        result.seconds["mapping"] = time.perf_counter() - start
        result.registered = {str(index): int(model.num_reg_images()) for index, model in (models or {}).items()}
    finally:
        pycolmap.logging.minloglevel = log_level
    return result
