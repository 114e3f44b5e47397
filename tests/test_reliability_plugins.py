"""Plugins and what they make, nothing lost, nothing silent, no traceback (issue 31): a name two plugins register is
refused naming both; ``model.init`` is checked like every checkpoint reader (hash, finite weights) and named as such; a
head's NaN or wrong shape names the head and its distribution; a checkpoint of an uninstalled plugin names it; help
works; the viewer stops on SIGINT/SIGTERM with 130/143; the docs list what a loss set reads."""

import dataclasses
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
import types
from pathlib import Path

import pytest
import torch

from gpnerf_core import ComponentSpec, DataTool, PerceptionHead, hookimpl
from gpnerf_core.commands import plugins as plugins_command
from gpnerf_core.commands import view as view_command
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import DataError, NonFiniteError, PluginError
from gpnerf_core.model.build import build_components
from gpnerf_core.model.checkpoint import FORMAT_VERSION, check_recorded_components, content_digest
from gpnerf_core.model.weights import init_weights
from gpnerf_core.registry.components import collect, register_config_options
from gpnerf_core.registry.plugins import PluginInfo, make_plugin_manager
from gpnerf_core.runtime.signals import Terminated
from gpnerf_core.tools.viewer.server import serve_until_stopped
from gpnerf_core.types import HeadOutput, LossInputs
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer
from training.test_resume import flip_byte_inside_tensor

DOCS = Path(__file__).resolve().parents[1] / "docs"


@dataclasses.dataclass
class UnetAgainConfig:
    name: str = "unet"


@dataclasses.dataclass
class NanHeadConfig:
    name: str = "reliability_nan_head"


@dataclasses.dataclass
class SmallHeadConfig:
    name: str = "reliability_small_head"


class ConstantHead(PerceptionHead):
    """Logits from a 1x1 convolution; ``poison`` makes them NaN, ``halve`` returns half the output size."""

    poison = False
    halve = False

    def __init__(self, in_dim, in_levels, num_outputs):
        super().__init__()
        self.k = num_outputs
        self.proj = torch.nn.Conv2d(in_dim, num_outputs, 1)

    @property
    def num_outputs(self):
        return self.k

    def forward(self, features, output_size):
        size = (output_size[0] // 2, output_size[1] // 2) if self.halve else output_size
        logits = torch.nn.functional.interpolate(self.proj(features), size=size, mode="bilinear")
        return HeadOutput(logits * float("nan") if self.poison else logits)


class NanHead(ConstantHead):
    poison = True


class SmallHead(ConstantHead):
    halve = True


def plugin_module(name, heads=(), tools=()):
    module = types.ModuleType(name)
    if heads:
        module.gpnerf_register_heads = hookimpl(lambda: list(heads))
    if tools:
        module.gpnerf_register_data_tools = hookimpl(lambda: list(tools))
    return module


def registry_with(*plugins):
    """The built-in plugins and ``plugins`` (``(module, PluginInfo)``), collected."""
    loaded = make_plugin_manager(autoload=False)
    for module, info in plugins:
        loaded.register(module, info)
    return collect(loaded)


DUPLICATE = PluginInfo("gpnerf_test_unet_again", "gpnerf-test-unet-again", "0.3")


# -- 1. a name two plugins register -------------------------------------------------------------------------------


def test_a_head_name_two_plugins_register_is_refused_naming_both_and_how_to_choose():
    registry = registry_with((plugin_module("unet_again", heads=[ComponentSpec("unet", ConstantHead,
                                                                               UnetAgainConfig)]), DUPLICATE))
    with pytest.raises(PluginError) as refused:
        registry.build("head", {"name": "unet"}, in_dim=8, in_levels=1, num_outputs=3)
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith("head 'unet' is offered by 2 plugins, gpnerf_plugins.heads.plugin (gpnerf-core ")
    assert "gpnerf_test_unet_again (gpnerf-test-unet-again 0.3)" in message
    assert "to use gpnerf_plugins.heads.plugin's: GPNERF_DISABLE_PLUGINS=gpnerf-test-unet-again" in message
    assert "to use gpnerf_test_unet_again's: GPNERF_DISABLE_PLUGINS=gpnerf_plugins.heads.plugin" in message
    problem = next(str(p) for p in registry.problems if p.component == "head/unet")
    assert "GPNERF_DISABLE_PLUGINS=gpnerf-test-unet-again keeps gpnerf_plugins.heads.plugin's" in problem
    assert registry.get("head", "per_pixel").provider == "gpnerf_plugins.heads.plugin"  # other names unaffected


def test_a_data_tool_name_two_plugins_register_runs_neither():
    tool = DataTool("check", lambda argv: 0, "a second check")
    registry = registry_with((plugin_module("check_again", tools=[tool]), DUPLICATE))
    assert "check" not in registry.data_tools
    assert [p.name for p in registry.clashes["data/check"]] == ["gpnerf_plugins.datasets.plugin", DUPLICATE.name]


def write_distribution(root, name, source, version="0.1"):
    module = f"gpnerf_test_{name}"
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{module}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: gpnerf-test-{name.replace('_', '-')}\n"
                                   f"Version: {version}\n")
    (info / "entry_points.txt").write_text(f"[gpnerf]\n{module} = {module}\n")


def gpnerf(*args, cwd, plugin_path=None):
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    if plugin_path is None:
        env["GPNERF_DISABLE_PLUGIN_AUTOLOAD"] = "1"
    else:
        env["PYTHONPATH"] = os.pathsep.join([str(plugin_path), env.get("PYTHONPATH", "")])
    env["GPNERF_CACHE"] = str(cwd / "cache")
    return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_run_with_a_clashing_head_is_one_line_before_anything_is_written(tmp_path):
    write_distribution(tmp_path, "unet_again", """
        import dataclasses
        from gpnerf_core import ComponentSpec, hookimpl
        from gpnerf_plugins.heads.unet import UNetHead

        @dataclasses.dataclass
        class Config:
            name: str = "unet"

        @hookimpl
        def gpnerf_register_heads():
            return [ComponentSpec("unet", UNetHead, Config)]
    """)
    result = gpnerf("run", "+head=unet", "+loss=dgs", "threads=1", f"out_dir={tmp_path / 'run'}", cwd=tmp_path,
                    plugin_path=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: head 'unet' is offered by 2 plugins")
    assert "gpnerf_test_unet_again (gpnerf-test-unet-again 0.1)" in result.stderr
    assert not (tmp_path / "run").exists()


# -- 2, 3. model.init: the content hash, finite weights, named as model.init=<file> -------------------------------


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny config and a gpnerf-core checkpoint of its untrained model (a minimal one: what model.init reads)."""
    root = tmp_path_factory.mktemp("reliability_plugins")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root / 'scenes'}",
                   "train.steps=1"])
    model = build_components(cfg).model
    return root, cfg, model


def save_state(path, weights, components=None):
    state = {"format": FORMAT_VERSION, "model": weights, "weight_average": None, "overrides": [],
             "config": "", "components": components or {}}
    state["content_sha256"] = content_digest(state)
    torch.save(state, path)
    return path


def test_model_init_of_a_damaged_checkpoint_is_refused_naming_model_init(tiny, tmp_path):
    _, _, model = tiny
    damaged = save_state(tmp_path / "damaged.pt", model.state_dict())
    flip_byte_inside_tensor(damaged)
    with pytest.raises(DataError, match=rf"^model\.init={re.escape(str(damaged))} is damaged: its contents do not "):
        init_weights(model, damaged)
    (tmp_path / "truncated.pt").write_bytes(damaged.read_bytes()[:200])
    with pytest.raises(DataError, match=r"^model\.init=.*truncated\.pt could not be read"):
        init_weights(model, tmp_path / "truncated.pt")


def test_model_init_with_a_nan_weight_is_refused_naming_the_file_and_the_tensor(tiny, tmp_path):
    _, _, model = tiny
    weights = {key: value.clone() for key, value in model.state_dict().items()}
    first = next(key for key, value in weights.items() if value.is_floating_point())
    weights[first].view(-1)[0] = float("nan")
    path = save_state(tmp_path / "nan.pt", weights)  # a valid hash: the file is what was saved
    before = {key: value.clone() for key, value in model.state_dict().items()}
    with pytest.raises(DataError) as refused:
        init_weights(model, path)
    assert str(refused.value).startswith(f"model.init={path}: tensor {first!r} is not finite (1 NaN, 0 Inf of ")
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # nothing half-loaded


# -- 4. a head's NaN or wrong shape, named where it is made ----------------------------------------------------------


NAN_PLUGIN = PluginInfo("gpnerf_test_nan_head", "gpnerf-test-nan-head", "0.7")


@pytest.fixture(scope="module")
def guarded_registry():
    registry = registry_with((plugin_module("nan_heads", heads=[
        ComponentSpec("reliability_nan_head", NanHead, NanHeadConfig),
        ComponentSpec("reliability_small_head", SmallHead, SmallHeadConfig),
    ]), NAN_PLUGIN))
    register_config_options(registry)
    return registry


def tiny_trainer(tiny, registry, head, run_dir):
    root, _, _ = tiny
    cfg = compose([f"+head={head}", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root / 'scenes'}",
                   "train.steps=1"])
    return make_trainer(cfg, run_dir, components=build_components(cfg, registry))


def test_a_heads_nan_is_named_with_the_head_and_its_distribution_not_the_loss(tiny, guarded_registry, tmp_path):
    trainer = tiny_trainer(tiny, guarded_registry, "reliability_nan_head", tmp_path / "run")
    with pytest.raises(NonFiniteError) as stopped:
        trainer.fit(progress=False)
    message = str(stopped.value)
    assert message.startswith("step 0: head 'reliability_nan_head' (plugin gpnerf_test_nan_head, gpnerf-test-nan-head "
                              "0.7) returned logits that are not finite (")
    assert "from finite input features" in message and "loss term" not in message
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_head_output_of_the_wrong_shape_names_the_head_and_both_shapes(tiny, guarded_registry, tmp_path):
    trainer = tiny_trainer(tiny, guarded_registry, "reliability_small_head", tmp_path / "run")
    with pytest.raises(PluginError) as refused:
        trainer.fit(progress=False)
    message = str(refused.value)
    assert message.startswith("head 'reliability_small_head' (plugin gpnerf_test_nan_head, gpnerf-test-nan-head 0.7) "
                              "returned logits [1, ")
    assert re.search(r"HeadOutput\(logits=\[N, num_outputs, \*output_size\]\) = \[1, \d+, 32, 48\]", message)


# -- 5. the docs list what a loss set reads -----------------------------------------------------------------------


def test_the_plugin_docs_list_every_loss_inputs_field_with_shape_and_dtype():
    text = (DOCS / "plugins.md").read_text()
    rows: dict[str, str] = {}
    for m in re.finditer(r"^\| `([a-z_.]+)` \|.*$", text, re.MULTILINE):  # the first table naming a field: LossInputs'
        rows.setdefault(m.group(1), m.group(0))
    for field in dataclasses.fields(LossInputs):
        assert field.name in rows, field.name
        assert rows[field.name].count("|") >= 6, rows[field.name]  # name, shape, dtype, units, when present


# -- 6. help ------------------------------------------------------------------------------------------------------


def test_plugins_help_prints_usage_and_exits_0(capsys):
    assert plugins_command.main(["--help"]) == 0
    assert capsys.readouterr().out.startswith("usage: python -m gpnerf_core plugins")


def test_eval_help_needs_no_checkpoint(tmp_path):
    result = gpnerf("eval", "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Traceback" not in result.stderr and "checkpoint" in result.stdout


# -- 7. a checkpoint of an uninstalled plugin -----------------------------------------------------------------------


GONE = {"head": {"name": "gone_head", "provider": "gpnerf_test_gone", "version": "1.2",
                 "distribution": "gpnerf-test-gone"}}


def test_a_checkpoint_whose_plugin_is_not_installed_names_its_distribution(tmp_path):
    path = tmp_path / "gone.pt"
    with pytest.raises(PluginError) as refused:
        check_recorded_components({"components": GONE}, path)
    assert str(refused.value) == (f"head 'gone_head' of checkpoint {path} comes from gpnerf-test-gone 1.2 (plugin "
                                  "gpnerf_test_gone), which is not installed; pip install 'gpnerf-test-gone==1.2'")
    check_recorded_components({"components": {"head": {"name": "unet", "provider": "x", "version": "1"}}}, path)


def test_eval_of_such_a_checkpoint_is_one_line(tiny, tmp_path):
    _, _, model = tiny
    path = save_state(tmp_path / "gone.pt", model.state_dict(), GONE)
    result = gpnerf("eval", f"checkpoint={path}", cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr[-2000:]
    assert "comes from gpnerf-test-gone 1.2 (plugin gpnerf_test_gone), which is not installed" in result.stderr


# -- 8. commands that build nothing do not import third-party plugins ------------------------------------------------


def test_help_and_usage_errors_import_no_third_party_plugin(tmp_path):
    mark = tmp_path / "imported"
    write_distribution(tmp_path, "slow", f"""
        open({str(mark)!r}, "a").write("imported\\n")
    """)
    for args in (["plugins", "--help"], ["stress", "--help"], ["report", "--help"]):
        result = gpnerf(*args, cwd=tmp_path, plugin_path=tmp_path)
        assert result.returncode == 0, (args, result.stderr[-1000:])
        assert not mark.exists(), args
    assert gpnerf("plugins", cwd=tmp_path, plugin_path=tmp_path).returncode == 0 and mark.exists()  # it lists them


SLOW_PLUGIN = """
    import time
    from gpnerf_core import DataTool, hookimpl

    open({mark!r}, "a").write("imported\\n")

    @hookimpl
    def gpnerf_register_data_tools():
        return [DataTool("greet", lambda argv: print("hello", *argv) or 0, "say hello")]
"""


def test_listing_commands_import_a_plugin_only_until_the_index_knows_it(tmp_path):
    mark = tmp_path / "imported"
    write_distribution(tmp_path, "slow", SLOW_PLUGIN.format(mark=str(mark)))
    first = gpnerf("data", cwd=tmp_path, plugin_path=tmp_path)  # not indexed yet: every plugin is loaded
    assert first.returncode == 0 and "greet" in first.stdout and mark.read_text().count("imported") == 1
    assert (tmp_path / "cache" / "plugin_index.json").is_file()
    for args in (["data"], ["data", "check", "--help"], ["stress", "--list"]):
        result = gpnerf(*args, cwd=tmp_path, plugin_path=tmp_path)
        assert result.returncode == 0, (args, result.stderr[-1000:])
        assert mark.read_text().count("imported") == 1, f"{args} imported the plugin"
    assert "say hello" in gpnerf("data", cwd=tmp_path, plugin_path=tmp_path).stdout  # listed from the index
    greeted = gpnerf("data", "greet", "you", cwd=tmp_path, plugin_path=tmp_path)  # its own tool: imported to run
    assert greeted.returncode == 0 and greeted.stdout.strip() == "hello you"
    assert mark.read_text().count("imported") == 2
    source = tmp_path / "gpnerf_test_slow.py"  # an edited plugin module: its record is stale, it is loaded again
    source.write_text(source.read_text().replace("say hello", "say hello again"))
    assert "say hello again" in gpnerf("data", cwd=tmp_path, plugin_path=tmp_path).stdout
    assert mark.read_text().count("imported") == 3


# -- 9. the viewer stops on SIGINT (even inherited ignored) and SIGTERM ----------------------------------------------


class FakeServer:
    url = "http://127.0.0.1:0"
    stopped = False

    def stop(self):
        self.stopped = True


@pytest.mark.parametrize("signum, raised", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated)])
def test_the_viewer_stops_on_a_signal_even_when_sigint_was_inherited_ignored(signum, raised):
    inherited = signal.signal(signal.SIGINT, signal.SIG_IGN)
    previous_term = signal.getsignal(signal.SIGTERM)
    server = FakeServer()
    try:
        timer = threading.Timer(0.3, os.kill, (os.getpid(), signum))
        timer.start()
        with pytest.raises(raised):
            with view_command._stopped_by_signals():
                serve_until_stopped(server, threading.Event())
        timer.join()
        assert server.stopped
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # the inherited handlers come back
        assert signal.getsignal(signal.SIGTERM) is previous_term
    finally:
        signal.signal(signal.SIGINT, inherited)


# -- 10. torchrun's own report after the project's line ------------------------------------------------------------


def test_the_training_docs_say_which_line_under_torchrun_is_the_error():
    text = (DOCS / "training.md").read_text()
    section = text[text.index("**Which line is the error.**"):]
    section = section[:section.index("\n- ")]
    for named in ("ChildFailedError", "SignalException", "Root Cause", "`error: ...`", "exit code"):
        assert named in section, named
