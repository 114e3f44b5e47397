"""Presets a plugin ships (``gpnerf_config_searchpaths``): a third-party package's ``experiment/<name>.yaml`` is
``+experiment=<name>``, its ``scale/cpu/<model>.yaml`` sizes its family at ``scale=cpu``, and a preset with the path
of a built-in one is refused naming both. The packages are written by the tests and found through their entry
points, as an installed distribution's would be."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

import model_family
from pipeline_check import TINY_CLI, for_parts

TESTS = Path(__file__).resolve().parents[1]

PLUGIN = '''
from gpnerf_core import hookimpl


@hookimpl
def gpnerf_config_searchpaths():
    return ["pkg://{package}.conf"]
'''


def write_preset_package(root: Path, package: str, files: dict[str, str]) -> None:
    """A distribution ``package`` (entry point group ``gpnerf``) whose plugin returns its ``conf`` folder, holding
    ``files`` (path relative to it -> text)."""
    (root / package / "conf").mkdir(parents=True)
    (root / package / "__init__.py").write_text(PLUGIN.format(package=package))
    (root / package / "conf" / "__init__.py").write_text("")
    for name, text in files.items():
        (root / package / "conf" / name).parent.mkdir(parents=True, exist_ok=True)
        (root / package / "conf" / name).write_text(textwrap.dedent(text))
    info = root / f"{package}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {package.replace('_', '-')}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[gpnerf]\n{package} = {package}\n")


def gpnerf(*args, root, cwd):
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    env["PYTHONPATH"] = os.pathsep.join([str(root), str(TESTS), env.get("PYTHONPATH", "")])
    env["GPNERF_CACHE"] = str(cwd / "cache")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def presets(tmp_path_factory):
    """A package shipping an experiment and its family's CPU preset, beside the test family it sizes."""
    root = tmp_path_factory.mktemp("presets")
    write_preset_package(root, "gpnerf_test_presets", {
        "experiment/third_party_tiny.yaml": """\
            # @package _global_
            defaults:
              - /head: unet
              - /loss: dgs
            train:
              steps: 1
            eval:
              save_images: 0
            """,
        "scale/cpu/pooled_views.yaml": """\
            # @package _global_
            model:
              hidden: 12
            """,
    })
    model_family.install(root)
    return root


def test_a_plugins_experiment_is_an_experiment_option(presets, tmp_path):
    result = gpnerf("run", "+experiment=third_party_tiny", *TINY_CLI, f"out_dir={tmp_path / 'run'}", root=presets,
                    cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["train"]["steps"] == 1 and config["head"]["name"] == "unet" and config["loss"]["name"] == "dgs"
    listed = gpnerf("plugins", root=presets, cwd=tmp_path)
    assert "pkg://gpnerf_test_presets.conf  (gpnerf_test_presets)" in listed.stdout


def test_a_plugin_familys_cpu_preset_sizes_it_at_scale_cpu(presets, tmp_path):
    tiny = for_parts(TINY_CLI, "feature_extractor")
    for scale, hidden in (("cpu", 12), ("paper", 32)):  # paper: the config's default
        out = tmp_path / scale
        result = gpnerf("run", "model=pooled_views", "+loss=ce", *tiny, "train.steps=1", f"scale={scale}",
                        f"out_dir={out}", root=presets, cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-2000:]
        assert yaml.safe_load((out / "config.yaml").read_text())["model"]["hidden"] == hidden


def test_a_preset_that_shadows_a_built_in_one_is_refused_naming_both(tmp_path):
    root = tmp_path / "packages"
    write_preset_package(root, "gpnerf_test_shadow", {"experiment/table4_id5.yaml": "# @package _global_\n"})
    result = gpnerf("run", "+head=unet", "+loss=dgs", *TINY_CLI, "train.steps=1", f"out_dir={tmp_path / 'run'}",
                    root=root, cwd=tmp_path)
    assert result.returncode == 2
    line = result.stderr.strip()
    assert "\n" not in line and line.startswith("error: config preset experiment/table4_id5.yaml of plugin "
                                                "gpnerf_test_shadow (pkg://gpnerf_test_shadow.conf) shadows the one "
                                                "of gpnerf-core's built-in conf/")
    assert "GPNERF_DISABLE_PLUGINS=gpnerf-test-shadow" in line
    assert not (tmp_path / "run").exists()
    listed = gpnerf("plugins", root=root, cwd=tmp_path)
    assert listed.returncode == 1 and "config preset experiment/table4_id5.yaml of plugin gpnerf_test_shadow" in \
        listed.stdout.split("\nproblems:\n", 1)[1]
