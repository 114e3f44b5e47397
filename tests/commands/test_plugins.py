"""Broken third-party plugins never take the tool down: each is reported (plugin, distribution, version, reason) by
`plugins`, which exits 1; the built-ins and the good plugins keep working; choosing a broken one is one line."""

import os
import re
import subprocess
import sys
import textwrap

import pytest

HEAD = """
import dataclasses
import torch
from gpnerf_core import ComponentSpec, PerceptionHead, hookimpl
from gpnerf_core.types import HeadOutput

@dataclasses.dataclass
class Config:
    name: str = "{name}"
    scale: float = 1.0

class Head(PerceptionHead):
    def __init__(self, scale, in_dim, in_levels, num_outputs):
        super().__init__()
        self.k = num_outputs
        self.proj = torch.nn.Conv2d(in_dim, num_outputs, 1)

    @property
    def num_outputs(self):
        return self.k

    def forward(self, features, output_size):
        logits = torch.nn.functional.interpolate(self.proj(features), size=output_size, mode="bilinear")
        return HeadOutput({logits})
"""

GOOD = HEAD + """
@hookimpl
def gpnerf_register_heads():
    return [ComponentSpec("good_head", Head, Config, "works")]
"""

BROKEN = {
    "import_error": "import no_such_dependency\n",
    "syntax_error": "def broken(:\n",
    "misspelled_hook": "from gpnerf_core import hookimpl\n@hookimpl\ndef gpnerf_register_haeds():\n    return []\n",
    "bad_hook_signature": "from gpnerf_core import hookimpl\n@hookimpl\ndef gpnerf_register_heads(extra):\n    return []\n",
    "duplicate_builtin": HEAD.replace("{name}", "unet") + "@hookimpl\ndef gpnerf_register_heads():\n"
                         "    return [ComponentSpec('unet', Head, Config, 'steals unet')]\n",
    "config_name_mismatch": HEAD.replace("{name}", "other") + "@hookimpl\ndef gpnerf_register_heads():\n"
                            "    return [ComponentSpec('mismatch_head', Head, Config)]\n",
    "narrow_factory": HEAD.replace("{name}", "narrow_head").replace(
        "def __init__(self, scale, in_dim, in_levels, num_outputs)", "def __init__(self, scale)")
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('narrow_head', Head, Config)]\n",
    "abstract_head": HEAD.replace("{name}", "abstract_head").replace("    def forward", "    def forward_")
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('abstract_head', Head, Config)]\n",
    "not_a_head": HEAD.replace("{name}", "plain_head").replace("class Head(PerceptionHead)", "class Head")
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('plain_head', Head, Config)]\n",
    "hook_raises": "from gpnerf_core import hookimpl\n@hookimpl\ndef gpnerf_register_losses():\n    raise RuntimeError('boom')\n",
    "not_a_spec": "from gpnerf_core import hookimpl\n@hookimpl\ndef gpnerf_register_losses():\n    return ['dgs']\n",
    "bad_name": HEAD.replace("{name}", "Fancy-Head") + "@hookimpl\ndef gpnerf_register_heads():\n"
                "    return [ComponentSpec('Fancy-Head', Head, Config)]\n",
    "config_without_default": HEAD.replace('    name: str = "{name}"\n    scale: float = 1.0',
                                           '    scale: float\n    name: str = "nodefault_head"')
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('nodefault_head', Head, Config)]\n",
    "unsupported_config_type": HEAD.replace("{name}", "tensor_head").replace("scale: float = 1.0",
                                                                              "scale: torch.Tensor = None")
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('tensor_head', Head, Config)]\n",
    "wrong_output_size": HEAD.replace("{name}", "small_head").replace("size=output_size", "scale_factor=1.0")
        + "@hookimpl\ndef gpnerf_register_heads():\n    return [ComponentSpec('small_head', Head, Config)]\n",
}
EXPECTED = {
    "import_error": "not loaded: import failed: ModuleNotFoundError: No module named 'no_such_dependency'",
    "syntax_error": "not loaded: import failed: SyntaxError",
    "misspelled_hook": "implements a hook gpnerf-core does not define",
    "bad_hook_signature": "not loaded: PluginValidationError",
    "duplicate_builtin": "head/unet rejected: the name is taken by 'gpnerf_plugins.heads.plugin'",
    "config_name_mismatch": "head/mismatch_head rejected: config Config.name defaults to 'other'",
    "narrow_factory": "head/narrow_head rejected: factory 'Head' cannot be called with the config fields",
    "abstract_head": "head/abstract_head rejected: Head leaves abstract members unimplemented: forward",
    "not_a_head": "head/plain_head rejected: Head does not subclass gpnerf_core.interfaces.head.PerceptionHead",
    "hook_raises": "not loaded: gpnerf_register_losses raised RuntimeError: boom",
    "not_a_spec": "loss rejected: gpnerf_register_losses returned str, expected ComponentSpec",
    "bad_name": "is not snake_case",
    "config_without_default": "head/nodefault_head rejected: config Config.scale has no default",
    "unsupported_config_type": "head/tensor_head rejected: config Config is not a valid Hydra schema",
}


def write_distribution(root, name, source):
    module = f"gpnerf_test_{name}"
    (root / f"{module}.py").write_text(textwrap.dedent(source).replace("{logits}", "logits"))
    info = root / f"gpnerf_test_{name}-0.{len(name)}.dist-info"
    info.mkdir()
    distribution = f"gpnerf-test-{name.replace('_', '-')}"
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {distribution}\nVersion: 0.{len(name)}\n")
    (info / "entry_points.txt").write_text(f"[gpnerf]\ngpnerf_test_{name} = {module}\n")


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory):
    root = tmp_path_factory.mktemp("third_party")
    write_distribution(root, "good", GOOD.replace("{name}", "good_head"))
    for name, source in BROKEN.items():
        write_distribution(root, name, source)
    return root


def gpnerf(*args, plugin_path, cwd, extra_env=None):
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    env["PYTHONPATH"] = os.pathsep.join([str(plugin_path), env.get("PYTHONPATH", "")])
    env["GPNERF_CACHE"] = str(cwd / "cache")
    env.update(extra_env or {})
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_plugins_lists_every_problem_and_exits_1(plugin_path, tmp_path):
    result = gpnerf("plugins", plugin_path=plugin_path, cwd=tmp_path)
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    problems = result.stdout.split("\nproblems:\n", 1)[1].splitlines()
    for name, fragment in EXPECTED.items():
        line = next((p for p in problems if f"gpnerf_test_{name} (gpnerf-test-{name.replace('_', '-')} 0." in p), "")
        assert fragment in line, (name, line)
    listed = result.stdout.split("\nproblems:\n", 1)[0]
    assert re.search(r"\nhead +good_head +gpnerf_test_good +0\.4 ", listed)
    assert re.search(r"\nhead +unet +gpnerf_plugins\.heads\.plugin ", listed)
    for name in ("narrow_head", "abstract_head", "plain_head", "mismatch_head", "nodefault_head", "tensor_head"):
        assert f" {name} " not in listed


def test_good_and_built_in_components_still_train_beside_broken_plugins(plugin_path, tmp_path):
    tiny = ["+loss=dgs", "dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6",
            "dataset.eval_every=3", "dataset.height=32", "dataset.width=48", "model.feature_extractor.widths=[8,8,8,16]",
            "model.feature_extractor.fpn_channels=4", "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2",
            "model.coarse_samples=6", "model.fine_samples=2", "model.num_source_views=2", "train.rays=16",
            "train.steps=1", "eval.max_views_per_scene=1", "eval.save_images=0", "threads=1"]
    result = gpnerf("run", "+head=good_head", *tiny, f"out_dir={tmp_path / 'good'}", plugin_path=plugin_path,
                    cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "good" / "metrics.json").is_file()
    rejected = gpnerf("run", "+head=narrow_head", *tiny, plugin_path=plugin_path, cwd=tmp_path)
    assert rejected.returncode == 2 and rejected.stderr.count("\n") == 1
    assert rejected.stderr.startswith("error: head 'narrow_head' was rejected: gpnerf_test_narrow_factory")
    missing = gpnerf("run", "+head=from_import_error", *tiny, plugin_path=plugin_path, cwd=tmp_path)
    assert missing.returncode == 2 and "; plugins that failed to load: " in missing.stderr
    assert "gpnerf_test_import_error (gpnerf-test-import-error 0.12): not loaded: import failed" in missing.stderr
    wrong = gpnerf("run", "+head=small_head", *tiny, f"out_dir={tmp_path / 'small'}", plugin_path=plugin_path,
                   cwd=tmp_path)
    assert wrong.returncode == 2 and "Traceback" not in wrong.stderr
    assert "head 'small_head' (plugin gpnerf_test_wrong_output_size, gpnerf-test-wrong-output-size 0.17) returned " \
           "logits [1, 9, 16, 24]; the PerceptionHead contract is HeadOutput(logits=[N, num_outputs, " \
           "*output_size]) = [1, 9, 32, 48]" in wrong.stderr


def test_disabling_a_broken_plugin_by_distribution_name(plugin_path, tmp_path):
    disabled = ",".join(f"gpnerf-test-{name.replace('_', '-')}" for name in BROKEN)
    result = gpnerf("plugins", plugin_path=plugin_path, cwd=tmp_path, extra_env={"GPNERF_DISABLE_PLUGINS": disabled})
    assert result.returncode == 0, result.stdout
    assert "\ndisabled:\n" in result.stdout and "gpnerf_test_import_error (gpnerf-test-import-error 0.12)" in result.stdout
