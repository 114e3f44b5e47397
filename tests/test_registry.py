import dataclasses
import textwrap
import types

import pytest
import torch

from gpnerf_core import ComponentSpec, PerceptionHead, hookimpl
from gpnerf_core.errors import ConfigError, PluginError
from gpnerf_core.registry.plugins import BUILTIN_PLUGINS, PluginInfo, make_plugin_manager
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.types import HeadOutput


@dataclasses.dataclass
class TinyHeadConfig:
    name: str = "tiny"
    width: int = 4


class TinyHead(PerceptionHead):
    def __init__(self, width, **runtime):
        super().__init__()
        self.width, self.runtime = width, runtime

    @property
    def num_outputs(self):
        return self.runtime.get("num_outputs", 1)

    def forward(self, features, output_size):
        return HeadOutput(torch.zeros(features.shape[0], self.num_outputs, *output_size))


def head_plugin(spec_name="tiny", config=TinyHeadConfig, factory=TinyHead):
    module = types.ModuleType(f"plugin_{spec_name}")

    @hookimpl
    def gpnerf_register_heads():
        return [ComponentSpec(spec_name, factory, config, "a tiny head")]

    module.gpnerf_register_heads = gpnerf_register_heads
    return module


def registry_with(*plugins):
    loaded = make_plugin_manager(builtins=(), autoload=False)
    for index, plugin in enumerate(plugins):
        loaded.register(plugin, PluginInfo(f"test_plugin_{index}", "test-dist", "9.9"))
    return collect(loaded)


def test_builtin_plugins_register_every_kind():
    loaded = make_plugin_manager(autoload=False)
    registry = collect(loaded)
    assert registry.problems == []
    for kind in KINDS:
        assert registry.names(kind), f"no built-in {kind}"
    assert {"unet", "per_pixel"} <= set(registry.names("head"))
    assert {"rgb", "ce", "sd", "dgs"} <= set(registry.names("loss"))
    assert set(loaded.plugins) == set(BUILTIN_PLUGINS)


def test_build_passes_config_fields_and_runtime_kwargs():
    registry = registry_with(head_plugin())
    head = registry.build("head", {"name": "tiny", "width": 7}, in_dim=12, in_levels=1, num_outputs=3)
    assert head.width == 7 and head.runtime == {"in_dim": 12, "in_levels": 1, "num_outputs": 3}


def test_a_duplicate_name_is_rejected_never_replaces_the_first_and_is_refused_when_chosen():
    registry = registry_with(head_plugin(), head_plugin())
    assert registry.components["head"]["tiny"].provider == "test_plugin_0"
    with pytest.raises(PluginError, match=r"^head 'tiny' is offered by 2 plugins, test_plugin_0 .* and test_plugin_1"):
        registry.get("head", "tiny")  # choosing it is refused: neither is picked silently
    [problem] = registry.problems
    assert problem.component == "head/tiny" and problem.plugin.name == "test_plugin_1"
    assert "taken by 'test_plugin_0'" in str(problem) and "test-dist 9.9" in str(problem)


def test_unknown_name_lists_known_names():
    registry = registry_with(head_plugin())
    with pytest.raises(ConfigError, match=r"unknown head 'fancy'; known head names: tiny"):
        registry.build("head", {"name": "fancy"})


def test_unknown_option_key_is_named():
    registry = registry_with(head_plugin())
    with pytest.raises(ConfigError, match=r"head.widht is not an option of head 'tiny'"):
        registry.build("head", {"name": "tiny", "widht": 3})


def test_config_name_must_match_spec_name():
    registry = registry_with(head_plugin("other", TinyHeadConfig))
    assert "other" not in registry.names("head")
    assert "defaults to 'tiny'; expected 'other'" in registry.problems[0].reason
    with pytest.raises(PluginError, match=r"head 'other' was rejected: test_plugin_0 \(test-dist 9.9\)"):
        registry.get("head", "other")


class AbstractHead(PerceptionHead):
    def __init__(self, width, **runtime):
        super().__init__()


class NarrowHead(PerceptionHead):
    def __init__(self, width):  # cannot take in_dim, in_levels, num_outputs
        super().__init__()

    num_outputs = 1

    def forward(self, features, output_size):
        return HeadOutput(features)


class NotAHead:
    def __init__(self, width, **runtime):
        pass


@pytest.mark.parametrize("factory, reason", [
    (AbstractHead, "leaves abstract members unimplemented: forward, num_outputs"),
    (NarrowHead, "cannot be called with the config fields and the pipeline's arguments (width, in_dim, in_levels"),
    (NotAHead, "does not subclass gpnerf_core.interfaces.head.PerceptionHead"),
])
def test_a_factory_the_pipeline_cannot_use_is_rejected_at_registration(factory, reason):
    registry = registry_with(head_plugin("tiny", TinyHeadConfig, factory), head_plugin("other", _config("other")))
    assert registry.names("head") == ["other"]  # the good plugin still works
    assert reason in registry.problems[0].reason


def build_abstract(width: int = 4, **runtime) -> AbstractHead:
    """The docs' pattern, a factory function, returning a class that leaves members abstract."""
    return AbstractHead(width)


def build_not_a_head(width: int = 4, **runtime) -> NotAHead:
    return NotAHead(width)


@pytest.mark.parametrize("factory, reason", [
    (build_abstract, "factory 'build_abstract' returns AbstractHead, which leaves abstract members unimplemented: "
                     "forward, num_outputs"),
    (build_not_a_head, "factory 'build_not_a_head' returns NotAHead, which does not subclass "
                       "gpnerf_core.interfaces.head.PerceptionHead"),
])
def test_a_factory_function_returning_an_unusable_class_is_rejected_at_registration(factory, reason):
    registry = registry_with(head_plugin("tiny", TinyHeadConfig, factory), head_plugin("other", _config("other")))
    assert registry.names("head") == ["other"]
    assert reason in registry.problems[0].reason


def _config(name):
    return dataclasses.make_dataclass(f"{name.title()}Config", [("name", str, name), ("width", int, 4)])


def test_a_hook_that_raises_or_returns_junk_is_recorded():
    raising = types.ModuleType("raising")
    raising.gpnerf_register_heads = hookimpl(lambda: 1 / 0)
    junk = types.ModuleType("junk")
    junk.gpnerf_register_losses = hookimpl(lambda: "dgs")
    registry = registry_with(raising, junk, head_plugin())
    reasons = [p.reason for p in registry.problems]
    assert "gpnerf_register_heads raised ZeroDivisionError: division by zero" in reasons
    assert "gpnerf_register_losses returned str, expected a list" in reasons
    assert registry.names("head") == ["tiny"]


def test_a_factory_that_fails_at_build_time_is_one_line_naming_its_plugin():
    class Exploding(TinyHead):
        def __init__(self, width, **runtime):
            raise ValueError("bad weights file\nsecond line")

    registry = registry_with(head_plugin("tiny", TinyHeadConfig, Exploding))
    with pytest.raises(PluginError) as error:
        registry.build("head", {"name": "tiny"}, in_dim=4, in_levels=1, num_outputs=2)
    assert str(error.value) == (
        "head 'tiny' (plugin test_plugin_0, test-dist 9.9) failed to build: ValueError: bad weights file"
    )


def test_misspelled_hook_leaves_out_that_plugin_only():
    module = types.ModuleType("typo_plugin")

    @hookimpl
    def gpnerf_register_haeds():
        return []

    module.gpnerf_register_haeds = gpnerf_register_haeds
    registry = registry_with(module, head_plugin())
    assert registry.names("head") == ["tiny"]
    [problem] = registry.problems
    assert problem.plugin.name == "test_plugin_0" and "gpnerf_register_haeds" in problem.reason
    assert "known hooks:" in problem.reason and "gpnerf_register_heads" in problem.reason


def write_distribution(root, dist, module, source, entry_name):
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{dist}-0.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.3\n")
    (info / "entry_points.txt").write_text(f"[gpnerf]\n{entry_name} = {module}\n")


GOOD_PLUGIN = """
    import dataclasses
    import torch
    from gpnerf_core import ComponentSpec, PerceptionHead, hookimpl
    from gpnerf_core.types import HeadOutput

    @dataclasses.dataclass
    class FancyConfig:
        name: str = "fancy_head"
        depth: int = 2

    class Fancy(PerceptionHead):
        def __init__(self, depth, in_dim, in_levels, num_outputs):
            super().__init__()
            self.depth, self.k = depth, num_outputs

        @property
        def num_outputs(self):
            return self.k

        def forward(self, features, output_size):
            return HeadOutput(torch.zeros(features.shape[0], self.k, *output_size))

    @hookimpl
    def gpnerf_register_heads():
        return [ComponentSpec("fancy_head", Fancy, FancyConfig, "third-party head")]
"""


def test_entry_point_plugins_load_and_broken_ones_are_reported(tmp_path, monkeypatch):
    write_distribution(tmp_path, "gpnerf_head_fancy", "gpnerf_head_fancy_plugin", GOOD_PLUGIN, "gpnerf_head_fancy")
    write_distribution(tmp_path, "gpnerf_broken", "gpnerf_broken_plugin", "import no_such_module\n", "gpnerf_broken")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    registry = collect(make_plugin_manager(autoload=True))
    entry = registry.get("head", "fancy_head")
    assert entry.provider == "gpnerf_head_fancy" and entry.version == "0.3"
    assert "unet" in registry.names("head")  # built-ins still load
    assert [p.plugin.name for p in registry.problems] == ["gpnerf_broken"]
    assert registry.problems[0].plugin.distribution == "gpnerf_broken"
    assert "import failed: ModuleNotFoundError: No module named 'no_such_module'" in registry.problems[0].reason
    with pytest.raises(ConfigError, match=r"unknown head 'broken'.*plugins that failed to load: gpnerf_broken"):
        registry.get("head", "broken")


def test_plugins_can_be_disabled_by_entry_point_or_distribution_name(tmp_path, monkeypatch):
    write_distribution(tmp_path, "gpnerf_head_fancy", "gpnerf_head_fancy_plugin", GOOD_PLUGIN, "gpnerf_head_fancy")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    for blocked in ("gpnerf_head_fancy", "GPNeRF-Head-Fancy"):
        monkeypatch.setenv("GPNERF_DISABLE_PLUGINS", blocked)
        registry = collect(make_plugin_manager(autoload=True))
        assert "fancy_head" not in registry.names("head")
        assert registry.disabled == ["gpnerf_head_fancy (gpnerf_head_fancy 0.3)"]


def test_autoload_can_be_disabled(tmp_path, monkeypatch):
    write_distribution(tmp_path, "gpnerf_head_fancy", "gpnerf_head_fancy_plugin", GOOD_PLUGIN, "gpnerf_head_fancy")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")
    registry = collect(make_plugin_manager())
    assert "fancy_head" not in registry.names("head")
    assert registry.disabled == ["every entry point (GPNERF_DISABLE_PLUGIN_AUTOLOAD is set)"]


def test_blocked_builtin_is_absent_and_named_when_its_component_is_asked_for():
    registry = collect(make_plugin_manager(autoload=False, blocked=("gpnerf_plugins.heads.plugin",)))
    assert registry.names("head") == [] and registry.disabled == ["gpnerf_plugins.heads.plugin"]
    with pytest.raises(ConfigError, match=r"unknown head 'unet'.*disabled plugins .*: gpnerf_plugins\.heads\.plugin"):
        registry.get("head", "unet")


def test_a_hook_without_hookimpl_is_reported_not_silently_ignored():
    module = types.ModuleType("unmarked_plugin")

    def gpnerf_register_heads():  # no @hookimpl: pluggy would skip it without a word
        return []

    module.gpnerf_register_heads = gpnerf_register_heads
    registry = registry_with(module, head_plugin())
    assert registry.names("head") == ["tiny"]
    [problem] = registry.problems
    assert "gpnerf_register_heads is not marked with @hookimpl" in problem.reason
