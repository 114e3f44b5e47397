"""``python -m gpnerf_core data`` tools of the built-in dataset plugins."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_plugins.datasets.common.layout_check import LayoutReport


def layout_checkers() -> dict[str, Callable[[Path], LayoutReport]]:
    """Checkers by layout name (imported lazily: checking one layout never imports the others)."""

    def replica(root: Path) -> LayoutReport:
        from gpnerf_plugins.datasets.replica.dataset import check_replica_layout

        return check_replica_layout(root)

    def replica_instance(root: Path) -> LayoutReport:
        from gpnerf_plugins.datasets.replica.dataset import check_replica_instance_layout

        return check_replica_instance_layout(root)

    def scannet(root: Path) -> LayoutReport:
        from gpnerf_plugins.datasets.scannet.dataset import check_scannet_layout

        return check_scannet_layout(root)

    return {"replica": replica, "replica_instance": replica_instance, "scannet": scannet}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one-line ConfigError instead of argparse's exit 2 with usage
        raise ConfigError(f"{self.prog}: {message}")


def check(argv: list[str]) -> int:
    checkers = layout_checkers()
    parser = _Parser(prog="gpnerf_core data check", description="Check a dataset folder against a layout.")
    parser.add_argument("root", type=Path)
    parser.add_argument("--layout", required=True, choices=sorted(checkers))
    args = parser.parse_args(argv)
    if not args.root.is_dir():
        raise DataError(f"{args.root}: expected a dataset folder, found nothing there")
    report = checkers[args.layout](args.root)
    print(report.format())
    return 0 if report.ok else 1


def make_embedded(argv: list[str]) -> int:
    from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes, EmbeddedScenesConfig

    defaults = EmbeddedScenesConfig()
    parser = _Parser(prog="gpnerf_core data make", description="Render the embedded scenes into the cache (or --root).")
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
