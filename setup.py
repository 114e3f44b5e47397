"""Maps the top-level conf/ folder to the importable package ``gpnerf_conf`` (pyproject.toml holds the rest).

setuptools' ``packages.find`` cannot rename a folder, so the package list is completed here. ``hydra_plugins`` is
Hydra's namespace package (no ``__init__.py``): gpnerf-core's search-path plugin lives in it.
"""

from setuptools import find_namespace_packages, find_packages, setup

packages = find_packages(".", include=["gpnerf_core*"]) + find_packages("plugins", include=["gpnerf_plugins*"])
packages += find_namespace_packages(".", include=["hydra_plugins.*"])
package_dir = {"gpnerf_plugins": "plugins/gpnerf_plugins", "gpnerf_conf": "conf"}
setup(packages=[*packages, "gpnerf_conf"], package_dir=package_dir)
