"""Registers the built-in datasets."""

from gpnerf_core import ComponentSpec, DataTool, hookimpl
from gpnerf_plugins.datasets import tools
from gpnerf_plugins.datasets.capture import colmap_import, prepare
from gpnerf_plugins.datasets.capture.dataset import CaptureScenes, CaptureScenesConfig
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes, EmbeddedScenesConfig
from gpnerf_plugins.datasets.replica.dataset import (
    ReplicaInstanceScenes,
    ReplicaInstanceScenesConfig,
    ReplicaScenes,
    ReplicaScenesConfig,
)
from gpnerf_plugins.datasets.scannet.dataset import ScanNetScenes, ScanNetScenesConfig


@hookimpl
def gpnerf_register_datasets() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "embedded",
            EmbeddedScenes,
            EmbeddedScenesConfig,
            "rooms of pybullet_data objects rendered on the CPU (Replica layout), generated once into a cache",
        ),
        ComponentSpec(
            "replica",
            ReplicaScenes,
            ReplicaScenesConfig,
            "Replica, Semantic-NeRF renders: 51 classes, held-out or paper-parity scene split",
        ),
        ComponentSpec(
            "replica_instance",
            ReplicaInstanceScenes,
            ReplicaInstanceScenesConfig,
            "Replica, DM-NeRF renders: raw instance ids, per-scene",
        ),
        ComponentSpec(
            "scannet",
            ScanNetScenes,
            ScanNetScenesConfig,
            "ScanNet scans (Semantic-Ray export layout), 20 benchmark classes",
        ),
        ComponentSpec(
            "capture",
            CaptureScenes,
            CaptureScenesConfig,
            "your own captures: nerfstudio transforms.json (PINHOLE/OPENCV), labels optional",
        ),
    ]


@hookimpl
def gpnerf_register_data_tools() -> list[DataTool]:
    return [
        DataTool("check", tools.check, "check a dataset folder: `data check <root> --layout replica|replica_instance|scannet|capture`"),
        DataTool("make", tools.make_embedded, "render the embedded scenes into the cache: `data make [--seed N ...]`"),
        DataTool(
            "prepare-scannet",
            tools.prepare_scannet,
            "turn a ScanNet scan (.sens + _2d-label-filt.zip) into the Semantic-Ray layout",
        ),
        DataTool(
            "import-colmap",
            colmap_import.main,
            "a COLMAP sparse model and its images to a capture: `data import-colmap <model> --images DIR --out DIR`",
        ),
        DataTool(
            "prepare-capture",
            prepare.main,
            "a video or photo folder to a capture by structure from motion: `data prepare-capture <src> --out DIR`",
        ),
    ]
