"""The config fields every built-in dataset shares: ``DatasetConfig``, subclassed by each dataset's config.

A dataset whose default differs overrides the field in its subclass (as the loss sets do with ``LossSetConfig``); its
constructor reads the defaults from its config (``root: str = ReplicaScenesConfig.root``), so each lives in one place.
What a shared field means for one dataset (what ``root`` holds, what ``""`` or a size of 0 selects) is in that config's
class docstring.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DatasetConfig:
    """Where the scenes are, the size frames are loaded at and the ray-sampling range."""

    name: str = ""
    """Registry name of the dataset (each subclass defaults it to its own)."""
    root: str = ""
    """Folder holding the dataset's scenes."""
    height: int = 240
    """Image height frames are loaded at, pixels."""
    width: int = 320
    """Image width frames are loaded at, pixels."""
    near: float = 0.1
    """Ray-sampling near bound, metres (training and evaluation alike)."""
    far: float = 6.0
    """Ray-sampling far bound, metres (training and evaluation alike)."""
    scenes: list[str] = field(default_factory=list)
    """Scenes to train on, by folder name under ``root``; empty = the dataset's shipped list (its protocol's)."""
    unseen_scenes: list[str] = field(default_factory=list)
    """Scenes never trained on, evaluated for generalization; empty = the dataset's shipped list."""
    validate: str = "quick"
    """Check the chosen scenes' files before training: quick (every file indexed, image sizes, poses finite and rigid),
    full (also decode every frame and check its labels) or off."""
