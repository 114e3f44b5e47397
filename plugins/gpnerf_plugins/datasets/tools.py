"""``python -m gpnerf_core data`` tools of the built-in dataset plugins."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from gpnerf_core import MAX_FAR, ArgumentParser, ConfigError, DataError
from gpnerf_plugins.datasets.common.layout_check import LayoutReport
from gpnerf_plugins.datasets.common.pose_report import RayRange


def layout_checkers() -> dict[str, Callable[[Path, float | None, float | None], LayoutReport]]:
    """Checkers by layout name, called with the root and the ray range pose sanity uses (None: the layout's dataset's
    default ``near``/``far``); imported lazily: checking one layout never imports the others."""

    def replica(root: Path, near: float | None, far: float | None) -> LayoutReport:
        from gpnerf_plugins.datasets.replica.dataset import ReplicaScenesConfig as Config, check_replica_layout

        return check_replica_layout(root, rays=_rays(Config.near, Config.far, near, far), hfov_deg=Config.hfov_deg)

    def replica_instance(root: Path, near: float | None, far: float | None) -> LayoutReport:
        from gpnerf_plugins.datasets.replica.dataset import ReplicaInstanceScenesConfig as Config
        from gpnerf_plugins.datasets.replica.dataset import check_replica_instance_layout

        rays = _rays(Config.near, Config.far, near, far)
        return check_replica_instance_layout(root, rays=rays, hfov_deg=Config.hfov_deg)

    def scannet(root: Path, near: float | None, far: float | None) -> LayoutReport:
        from gpnerf_plugins.datasets.scannet.dataset import ScanNetScenesConfig as Config, check_scannet_layout

        return check_scannet_layout(root, rays=_rays(Config.near, Config.far, near, far))

    def capture(root: Path, near: float | None, far: float | None) -> LayoutReport:
        from gpnerf_plugins.datasets.capture.check import check_capture_layout

        rays = None if near is None and far is None else _rays(near or 0.0, far or 0.0, near, far)
        return check_capture_layout(root, rays)

    return {"replica": replica, "replica_instance": replica_instance, "scannet": scannet, "capture": capture}


def _rays(default_near: float, default_far: float, near: float | None, far: float | None) -> RayRange:
    rays = RayRange(default_near if near is None else near, default_far if far is None else far)
    if not 0.0 < rays.near < rays.far <= MAX_FAR:
        raise ConfigError(f"--near {rays.near:g} --far {rays.far:g}: expected 0 < near < far <= {MAX_FAR:g} (metres)")
    return rays



def check(argv: list[str]) -> int:
    checkers = layout_checkers()
    parser = ArgumentParser(prog="gpnerf_core data check", description="Check a dataset folder against a layout.")
    parser.add_argument("root", type=Path)
    parser.add_argument("--layout", required=True, choices=sorted(checkers))
    parser.add_argument("--near", type=float, default=None, help="pose sanity's near bound, metres (default: the "
                        "dataset's dataset.near; a capture's own bounds)")
    parser.add_argument("--far", type=float, default=None, help="pose sanity's far bound, metres (default: the "
                        "dataset's dataset.far)")
    args = parser.parse_args(argv)
    if not args.root.is_dir():
        raise DataError(f"{args.root}: expected a dataset folder, found nothing there")
    report = checkers[args.layout](args.root, args.near, args.far)
    print(report.format())
    return 0 if report.ok else 1


def make_embedded(argv: list[str]) -> int:
    from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes, EmbeddedScenesConfig

    defaults = EmbeddedScenesConfig()
    parser = ArgumentParser(prog="gpnerf_core data make", description="Render the embedded scenes into the cache (or --root).")
    parser.add_argument("--root", default=defaults.root)
    for key in ("num_train_scenes", "num_unseen_scenes", "frames_per_scene", "height", "width", "seed"):
        parser.add_argument(f"--{key.replace('_', '-')}", dest=key, type=int, default=getattr(defaults, key))
    parser.add_argument("--textureless", action="store_true", help="one flat colour per surface instead of textures")
    args = vars(parser.parse_args(argv))
    dataset = EmbeddedScenes(**args)
    folder = dataset.prepare()
    print(f"embedded scenes ready in {folder}")
    return 0


def prepare_scannet(argv: list[str]) -> int:
    from gpnerf_plugins.datasets.scannet.prepare import main as prepare_main

    return prepare_main(argv)
