"""Example gpnerf-core plugin: Gaussian Grouping (Ye et al., ECCV 2024) as the model family ``gaussian_grouping``
(registered in ``plugin``), with its presets (``+experiment=gaussian_grouping``)."""

__version__ = "0.1.0"
