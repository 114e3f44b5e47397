import dataclasses
import textwrap
import types

import pytest

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_core.errors import ConfigError, PluginError
from gpnerf_core.registry import BUILTIN_PLUGINS, KINDS, collect, make_plugin_manager


@dataclasses.dataclass
class TinyHeadConfig:
    name: str = "tiny"
    width: int = 4


class TinyHead:
    def __init__(self, width, **runtime):
        self.width, self.runtime = width, runtime


def head_plugin(spec_name="tiny", config=TinyHeadConfig):
    module = types.ModuleType(f"plugin_{spec_name}")

    @hookimpl
    def gpnerf_register_heads():
        return [ComponentSpec(spec_name, TinyHead, config, "a tiny head")]

    module.gpnerf_register_heads = gpnerf_register_heads
    return module


def registry_with(*plugins):
    pm, problems, versions = make_plugin_manager(builtins=(), autoload=False)
    for index, plugin in enumerate(plugins):
        pm.register(plugin, name=f"test_plugin_{index}")
    return collect(pm, problems, versions)


def test_builtin_plugins_register_every_kind():
    pm, problems, versions = make_plugin_manager(autoload=False)
    registry = collect(pm, problems, versions)
    assert problems == []
    for kind in KINDS:
        assert registry.names(kind), f"no built-in {kind}"
    assert {"unet", "per_pixel"} <= set(registry.names("head"))
    assert {"rgb", "ce", "sd", "dgs"} <= set(registry.names("loss"))
    assert set(versions) == set(BUILTIN_PLUGINS)


def test_build_passes_config_fields_and_runtime_kwargs():
    registry = registry_with(head_plugin())
    head = registry.build("head", {"name": "tiny", "width": 7}, in_dim=12)
    assert head.width == 7 and head.runtime == {"in_dim": 12}


def test_duplicate_names_fail_naming_both_providers():
    with pytest.raises(PluginError, match=r"duplicate head 'tiny'.*test_plugin_0.*test_plugin_1"):
        registry_with(head_plugin(), head_plugin())


def test_unknown_name_lists_known_names():
    registry = registry_with(head_plugin())
    with pytest.raises(ConfigError, match=r"unknown head 'fancy'; known head names: tiny"):
        registry.build("head", {"name": "fancy"})


def test_unknown_option_key_is_named():
    registry = registry_with(head_plugin())
    with pytest.raises(ConfigError, match=r"head.widht is not an option of head 'tiny'"):
        registry.build("head", {"name": "tiny", "widht": 3})


def test_config_name_must_match_spec_name():
    with pytest.raises(PluginError, match="defaults to 'tiny'; expected 'other'"):
        registry_with(head_plugin("other", TinyHeadConfig))


def test_misspelled_hook_is_an_error():
    module = types.ModuleType("typo_plugin")

    @hookimpl
    def gpnerf_register_haeds():
        return []

    module.gpnerf_register_haeds = gpnerf_register_haeds
    pm, _, _ = make_plugin_manager(builtins=(), autoload=False)
    pm.register(module, name="typo")
    with pytest.raises(Exception, match="haeds"):
        pm.check_pending()


def write_distribution(root, dist, module, source, entry_name):
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{dist}-0.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.3\n")
    (info / "entry_points.txt").write_text(f"[gpnerf]\n{entry_name} = {module}\n")


GOOD_PLUGIN = """
    import dataclasses
    from gpnerf_core import ComponentSpec, hookimpl

    @dataclasses.dataclass
    class FancyConfig:
        name: str = "fancy_head"
        depth: int = 2

    class Fancy:
        def __init__(self, depth, **runtime):
            self.depth = depth

    @hookimpl
    def gpnerf_register_heads():
        return [ComponentSpec("fancy_head", Fancy, FancyConfig, "third-party head")]
"""


def test_entry_point_plugins_load_and_broken_ones_are_reported(tmp_path, monkeypatch):
    write_distribution(tmp_path, "gpnerf_head_fancy", "gpnerf_head_fancy_plugin", GOOD_PLUGIN, "gpnerf_head_fancy")
    write_distribution(tmp_path, "gpnerf_broken", "gpnerf_broken_plugin", "import no_such_module\n", "gpnerf_broken")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    pm, problems, versions = make_plugin_manager(autoload=True)
    registry = collect(pm, problems, versions)
    entry = registry.get("head", "fancy_head")
    assert entry.provider == "gpnerf_head_fancy" and entry.version == "0.3"
    assert "unet" in registry.names("head")  # built-ins still load
    assert [name for name, _ in registry.problems] == ["gpnerf_broken"]
    assert "no_such_module" in registry.problems[0][1]


def test_autoload_can_be_disabled(tmp_path, monkeypatch):
    write_distribution(tmp_path, "gpnerf_head_fancy", "gpnerf_head_fancy_plugin", GOOD_PLUGIN, "gpnerf_head_fancy")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")
    registry = collect(*make_plugin_manager())
    assert "fancy_head" not in registry.names("head")


def test_blocked_builtin_is_absent():
    registry = collect(*make_plugin_manager(autoload=False, blocked=("gpnerf_plugins.heads.plugin",)))
    assert registry.names("head") == []
