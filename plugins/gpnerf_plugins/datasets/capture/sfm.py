"""Structure from motion through pycolmap: SIFT features, sequential or exhaustive matching, incremental mapping.

- Features: one camera for all frames (``CameraMode.SINGLE``) of ``SfmOptions.camera_model``, its parameters refined
  by bundle adjustment; or, with ``SfmOptions.intrinsics``, a PINHOLE camera with those parameters held fixed.
- Matching: ``sequential`` (each frame against its neighbours in name order: videos) or ``exhaustive`` (every pair:
  small photo sets).
- Mapping: ``incremental_mapping``; it may split the frames into several models (the import takes the largest).

The stages run in a child process (multiprocessing, spawn) that ignores SIGINT and dies silently on SIGTERM: Ctrl-C
or SIGTERM reaches this process, which kills the child (nothing in it needs cleaning: it writes only into ``work``,
which the caller deletes) and raises the interruption at once. Signalling inside a native pycolmap call instead
(a ``CancellationToken`` from a worker thread, or glog's own SIGTERM handler) aborted the process with a native stack
dump and left the staging folder behind. COLMAP's log is kept to errors unless ``SfmOptions.verbose``.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from tqdm import tqdm

from gpnerf_core import ConfigError, DataError, GpnerfError
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
ANSWER_POLL_SECONDS = 0.2
"""How often the waiting parent wakes up (a Ctrl-C is acted on within this time)."""


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


def _stage(bar: tqdm | None, function: Callable[..., Any], stage: str, **kwargs: Any) -> Any:
    """``function(**kwargs)``; a failure is one ``DataError`` naming the stage."""
    try:
        return function(**kwargs)
    except Exception as exc:
        raise DataError(f"structure from motion failed in {stage} ({one_line_error(exc)})") from None
    finally:
        if bar is not None:
            bar.refresh()


def run_sfm(images: Path, names: list[str], work: Path, options: SfmOptions, progress: bool | None = None) -> SfmResult:
    """Run SfM on ``images/<names>`` with its database and models under ``work``; models go to ``work/sparse``.

    The stages run in a child process (``_sfm_process``); an interruption (``KeyboardInterrupt``, SIGTERM's
    exception) kills it and is raised here once it is gone, so the caller may delete ``work`` at once.

    Raises:
        ConfigError: an unknown camera model, matcher or device, or CUDA asked of a CPU build.
        DataError: a pycolmap stage failed (its message on one line), or the child process died.
    """
    pycolmap = load_pycolmap()
    if options.intrinsics is None and options.camera_model not in CAMERA_MODELS:
        raise ConfigError(f"--camera-model {options.camera_model}; expected one of {', '.join(CAMERA_MODELS)}")
    if options.matcher not in MATCHERS:
        raise ConfigError(f"--matcher {options.matcher}; expected one of {', '.join(MATCHERS)}")
    _device(pycolmap, options.device)
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_sfm_process, args=(sender, images, names, work, options, progress),
                              name="pycolmap-sfm", daemon=True)
    try:
        with _interruptions_held():
            process.start()
        sender.close()
        while not receiver.poll(ANSWER_POLL_SECONDS):
            pass  # a pending interruption is raised between polls, whichever thread the signal reached
        try:
            kind, value = receiver.recv()
        except EOFError:  # the child died before answering
            process.join()
            raise DataError(f"structure from motion stopped: its process ended without a result "
                            f"({_exit_status(process.exitcode)})") from None
        process.join()
    except BaseException:
        if process.pid is not None and process.exitcode is None:
            process.kill()  # nothing to clean up in it: it writes only into ``work``
            process.join()
        raise
    finally:
        receiver.close()
        sender.close()
    if kind == "error":
        raise value
    return value


@contextlib.contextmanager
def _interruptions_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while the child starts: it inherits the blocked mask (so none lands in its Python
    start-up, before it ignores them) and this process receives them once the block ends, none lost."""
    held = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _exit_status(code: int | None) -> str:
    if code is not None and code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return f"exit code {code}"


def _sfm_process(sender: Any, images: Path, names: list[str], work: Path, options: SfmOptions,
                 progress: bool | None) -> None:
    """The child process: the stages, answered through ``sender`` as ``("ok", SfmResult)`` or ``("error", exc)``.

    SIGINT is ignored (Ctrl-C reaches the whole process group; the parent decides) and SIGTERM ends it silently,
    instead of the stack dump of the handler glog installs when pycolmap is imported."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    pycolmap = load_pycolmap()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    tqdm.set_lock(threading.RLock())  # not tqdm's default semaphore: a killed child would leave it to the tracker's warning
    try:
        answer: tuple[str, Any] = ("ok", _run_stages(pycolmap, images, names, work, options, progress))
    except GpnerfError as exc:
        answer = ("error", exc)
    except Exception as exc:
        answer = ("error", DataError(f"structure from motion failed ({one_line_error(exc)})"))
    sender.send(answer)
    sender.close()


def _run_stages(pycolmap: Any, images: Path, names: list[str], work: Path, options: SfmOptions,
                progress: bool | None) -> SfmResult:
    """Features, matching and mapping (in the child process)."""
    device = _device(pycolmap, options.device)
    database, sparse = work / "database.db", work / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    disable = None if progress is None else not progress
    result = SfmResult(sparse, {})
    if not options.verbose:
        pycolmap.logging.minloglevel = 2  # errors only
    pycolmap.set_random_seed(options.seed)
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
            _stage(bar, pycolmap.extract_features, "feature extraction", database_path=database, image_path=images,
                   image_names=batch, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                   extraction_options=extraction, device=device)
            reader.existing_camera_id = 1  # later batches share the first batch's camera
            bar.update(len(batch))
    result.seconds["features"] = time.perf_counter() - start

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.threads
    match = pycolmap.match_sequential if options.matcher == "sequential" else pycolmap.match_exhaustive
    start = time.perf_counter()
    with tqdm(total=1, desc=f"matching ({options.matcher})", unit="stage", disable=disable) as bar:
        _stage(bar, match, "matching", database_path=database, matching_options=matching, device=device)
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
        models = _stage(bar, pycolmap.incremental_mapping, "mapping", database_path=database, image_path=images,
                        output_path=sparse, options=mapping, next_image_callback=lambda: bar.update(1))
    result.seconds["mapping"] = time.perf_counter() - start
    result.registered = {str(index): int(model.num_reg_images()) for index, model in (models or {}).items()}
    return result
