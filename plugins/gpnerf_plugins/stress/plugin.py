"""Registers the built-in stress cases."""

from gpnerf_core import StressCase, hookimpl
from gpnerf_plugins.stress.data_cases import Textureless, UnseenScenes
from gpnerf_plugins.stress.geometry_cases import (
    Baseline,
    OneWrongCamera,
    RotationNoise,
    SourceViewCount,
    TranslationNoise,
)
from gpnerf_plugins.stress.image_cases import Blur, Exposure, GaussianNoise, Jpeg
from gpnerf_plugins.stress.target_cases import ViewDistance


@hookimpl
def gpnerf_register_stress_cases() -> list[StressCase]:
    return [
        SourceViewCount(),
        Baseline(),
        RotationNoise(),
        TranslationNoise(),
        OneWrongCamera(),
        GaussianNoise(),
        Blur(),
        Jpeg(),
        Exposure(),
        Textureless(),
        UnseenScenes(),
        ViewDistance(),
    ]
