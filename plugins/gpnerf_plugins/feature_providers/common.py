"""What the built-in providers share: a weights file's hash, a package's version, the one-line refusals."""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
from pathlib import Path

from gpnerf_core import ConfigError, from_launch_dir


def file_hash(path: Path) -> str:
    """The SHA-256 of a file's bytes, 16 hex digits (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def package_version(distribution: str) -> str:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def require_package(module: str, provider: str, install: str, weights: str = "") -> None:
    """Refuse in one line when ``module`` cannot be imported, naming the provider, what to install and (when given)
    the weights file it would read."""
    if importlib.util.find_spec(module) is None:
        also = f" (it would read the weights file {weights})" if weights else ""
        raise ConfigError(f"feature_provider={provider} needs the Python package {module!r}, which is not "
                          f"installed{also}: {install}")


def weights_file(given: str, key: str, provider: str, install: str) -> Path:
    """The weights file ``given`` for ``key`` (a relative path from the launch directory), refused naming the path
    when it is empty or not a file."""
    if not given:
        raise ConfigError(f"{key} is empty; feature_provider={provider} builds its model from a local weights file "
                          f"(nothing is downloaded): {key}=/path/to/weights ({install})")
    path = from_launch_dir(given)
    if not path.is_file():
        raise ConfigError(f"{key}={given}: no such weights file ({path}); feature_provider={provider} builds its "
                          f"model from a local weights file, nothing is downloaded ({install})")
    return path
