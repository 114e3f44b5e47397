"""The contract kit catches each broken rule, names the check and the shapes, and leaves correct components alone."""

import dataclasses
import math
import textwrap
import types
from dataclasses import replace
from typing import Callable, Tuple

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from gpnerf_core import (
    Capabilities,
    ComponentSpec,
    DepthBelief,
    DepthSource,
    FeatureExtractor,
    FieldAggregator,
    LossSet,
    PerceptionHead,
    RayAggregator,
    SceneDataset,
    StressCase,
    ViewSelector,
    hookimpl,
    source_depth_belief,
)
from gpnerf_core.errors import ConfigError
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.testing import CHECKS, ContractError, check_plugin, plugin_checks
from gpnerf_core.testing.checks import RUNTIME
from gpnerf_core.types import FeatureMaps, FieldBlockOutput, HeadOutput, RayBlockOutput, RayReadout

pytest_plugins = ["pytester"]


def plugin(kind, *specs, module_name="kit_test_plugin"):
    """A plugin module registering ``specs`` (``(name, factory, config)``) under ``kind``."""
    module = types.ModuleType(module_name)

    def register():
        return [ComponentSpec(name, factory, config) for name, factory, config in specs]

    setattr(module, KINDS[kind].hook, hookimpl(register))
    return module


def config(name, **fields):
    """A config dataclass whose ``name`` defaults to ``name``; ``fields`` are ``(type, default)``."""
    items = [("name", str, name)]
    items += [(key, kind, dataclasses.field(default=value)) for key, (kind, value) in fields.items()]
    return dataclasses.make_dataclass(f"Config_{name}", items)


def failures(kind, factory, component_config=None, name="under_test"):
    """``{check: message}`` of the failed checks of one component."""
    module = plugin(kind, (name, factory, component_config or config(name)))
    results = check_plugin(module, raise_on_failure=False)
    assert {r.component for r in results} == {f"{kind}/{name}"}
    return {r.check: r.message for r in results if r.failed}


# ------------------------------------------------------------------------------------------------------------ heads


class GoodHead(PerceptionHead):
    def __init__(self, *, in_dim, in_levels, num_outputs, **_options):
        super().__init__()
        self.classes = num_outputs
        self.conv = nn.Conv2d(in_dim, num_outputs, 1)

    @property
    def num_outputs(self):
        return self.classes

    def decode(self, features):
        return self.conv(features)

    def resize(self, logits, size):
        return F.interpolate(logits, size=size, mode="bilinear", align_corners=False)

    def forward(self, features, output_size):
        return HeadOutput(self.resize(self.decode(features), output_size))


class NoResize(GoodHead):
    def resize(self, logits, size):
        return logits


class UnusedParameter(GoodHead):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.spare = nn.Parameter(torch.zeros(3))


class NanOnZeros(GoodHead):
    def decode(self, features):
        return self.conv(features / features.norm(dim=1, keepdim=True))


class LyingNumOutputs(GoodHead):
    num_outputs = property(lambda self: 3)


class DropoutInEval(GoodHead):
    def decode(self, features):
        return self.conv(F.dropout(features, 0.5, training=True))


class DoubleLogits(GoodHead):
    def decode(self, features):
        return self.conv(features).double()


class IgnoresInput(GoodHead):
    def decode(self, features):
        return self.conv.bias.view(1, -1, 1, 1).expand(features.shape[0], -1, *features.shape[-2:])


class NeedsTupleKernel(GoodHead):
    def __init__(self, *, kernel, **kwargs):
        if not isinstance(kernel, tuple):
            raise TypeError(f"kernel must be a tuple, got {type(kernel).__name__}")
        super().__init__(**kwargs)


class TakesNoRuntime(GoodHead):
    def __init__(self):
        super().__init__(in_dim=1, in_levels=1, num_outputs=1)


@pytest.mark.parametrize("factory, checks", [
    (NoResize, {"output size"}),
    (UnusedParameter, {"gradients"}),
    (NanOnZeros, {"degenerate inputs"}),
    (LyingNumOutputs, {"num_outputs"}),
    (DropoutInEval, {"train and eval"}),
    (DoubleLogits, {"dtype"}),
    (IgnoresInput, {"gradients", "degenerate inputs"}),  # no gradient reaches the features, zero or not
])
def test_each_broken_head_fails_exactly_its_checks(factory, checks):
    assert set(failures("head", factory)) == checks


def test_a_wrong_output_size_names_the_component_the_check_and_the_shapes():
    message = failures("head", NoResize)["output size"]
    assert message == (
        "head 'under_test' (plugin kit_test_plugin unknown): check 'output size' failed: logits [2, 51, 7, 9], "
        "expected [2, 51, 37, 45] for features [2, 32, 7, 9] and output_size (37, 45)"
    )


def test_gradient_failures_name_the_parameter_or_the_input():
    assert "no gradient reached spare" in failures("head", UnusedParameter)["gradients"]
    assert "conv.weight, input features" in failures("head", IgnoresInput)["gradients"]


def test_a_config_that_does_not_round_trip_is_caught():
    tuple_config = config("under_test", kernel=(Tuple[int, int], (3, 3)))
    message = failures("head", NeedsTupleKernel, tuple_config)["config round trip"]
    assert message.endswith("building from the round-tripped config raised TypeError: kernel must be a tuple, got list")
    callable_config = config("under_test", activation=(Callable, F.relu))
    assert "OmegaConf cannot represent" in failures("head", GoodHead, callable_config)["config round trip"]


def test_a_factory_the_pipeline_cannot_call_fails_registration():
    [result] = check_plugin(plugin("head", ("narrow", TakesNoRuntime, config("narrow"))), raise_on_failure=False)
    assert result.check == "registration" and result.component == "head/narrow" and result.failed
    assert "cannot be called with the config fields and the pipeline's arguments" in result.message


def test_configs_for_a_component_that_failed_registration_report_the_failure_not_a_key_error():
    module = plugin("head", ("narrow", TakesNoRuntime, config("narrow")))
    [result] = check_plugin(module, configs={"head/narrow": {"channels": 2}}, raise_on_failure=False)
    assert result.check == "registration" and "cannot be called with the config fields" in result.message


def test_a_plugin_without_components_fails_registration():
    [result] = check_plugin(types.ModuleType("empty_plugin"), raise_on_failure=False)
    assert result.check == "registration" and "registers no components" in result.message


def test_check_plugin_raises_one_error_listing_every_failure():
    module = plugin("head", ("unused", UnusedParameter, config("unused")), ("nan", NanOnZeros, config("nan")))
    with pytest.raises(ContractError) as caught:
        check_plugin(module)
    lines = str(caught.value).splitlines()
    assert len(lines) == 2 == len(caught.value.results)
    assert lines[0].startswith("head 'nan' (plugin kit_test_plugin unknown): check 'degenerate inputs' failed: ")
    assert lines[1].startswith("head 'unused' (plugin kit_test_plugin unknown): check 'gradients' failed: ")


def test_a_component_that_does_not_build_skips_its_other_checks():
    def explode(**_):
        raise RuntimeError("boom")

    results = check_plugin(plugin("head", ("broken", explode, config("broken"))), raise_on_failure=False)
    assert [r.check for r in results if r.failed] == ["build"]
    assert results[0].message == ("head 'broken' (plugin kit_test_plugin unknown): check 'build' failed: building with "
                                  "in_dim=32, in_levels=4, num_outputs=3 raised RuntimeError: boom")
    assert {r.outcome for r in results[1:]} == {"skipped"}


def test_configs_replace_defaults_and_unknown_keys_are_refused():
    sized = config("under_test", channels=(int, 4))
    seen = []

    class Recording(GoodHead):
        def __init__(self, **kwargs):
            seen.append(kwargs["channels"])
            super().__init__(**kwargs)

    module = plugin("head", ("under_test", Recording, sized))
    check_plugin(module, configs={"head/under_test": {"channels": 2}})
    assert set(seen) == {2}
    with pytest.raises(KeyError, match="head/other"):
        plugin_checks(module, configs={"head/other": {}})


# ------------------------------------------------------------------------------------------------------- extractors


class GoodExtractor(FeatureExtractor):
    levels = 2

    def __init__(self, width=8):
        super().__init__()
        self.width = width
        self.radiance = nn.Conv2d(3, width, 3, stride=4, padding=1)
        self.semantic = nn.Conv2d(3, 2 * width, 3, stride=2, padding=1)

    radiance_dim = property(lambda self: self.width)
    semantic_dim = property(lambda self: 2 * self.width)
    semantic_levels = property(lambda self: self.levels)

    def check_size(self, images):
        if images.shape[-1] % 16 or images.shape[-2] % 16:
            raise ConfigError(f"image size {tuple(images.shape[-2:])} is not a multiple of 16")

    def forward(self, images):
        self.check_size(images)
        return FeatureMaps(self.radiance(images), self.semantic(images))


class LyingRadianceWidth(GoodExtractor):
    radiance_dim = property(lambda self: self.width + 1)


class UnevenLevels(GoodExtractor):
    levels = 3


class CrashesOnOtherSizes(GoodExtractor):
    def check_size(self, images):
        images.unflatten(-1, (-1, 16))  # RuntimeError unless W % 16 == 0


# ------------------------------------------------------------------------------------------------------ aggregators


class GoodField(FieldAggregator):
    view_axis = 2

    def __init__(self, *, in_dim, width=8):
        super().__init__()
        self.proj = nn.Linear(in_dim, width)
        self.score = nn.ModuleList(nn.Linear(width, width) for _ in range(2))

    width = property(lambda self: self.proj.out_features)
    attention_channels = property(lambda self: self.proj.out_features)
    num_blocks = property(lambda self: len(self.score))

    def begin(self, features, samples, rays):
        per_view = self.proj(features.rgb_features)
        return per_view.mean(2), (per_view, features.visible)

    def block(self, index, tokens, context):
        per_view, visible = context
        logits = self.score[index](per_view + tokens[:, :, None]).masked_fill(~visible[..., None], -1e4)
        attention = torch.softmax(logits, dim=self.view_axis)
        return FieldBlockOutput(tokens + (attention * per_view).sum(2), attention)


class SoftmaxOverChannels(GoodField):
    view_axis = -1


class GoodRay(RayAggregator):
    def __init__(self, *, in_dim, num_blocks, heads=2):
        super().__init__()
        self.heads = heads
        self.qk = nn.ModuleList(nn.Linear(in_dim, 2 * in_dim) for _ in range(num_blocks))
        self.rgb = nn.Linear(in_dim, 3)

    num_heads = property(lambda self: self.heads)
    num_blocks = property(lambda self: len(self.qk))

    def block(self, index, tokens):
        r, s, d = tokens.shape
        q, k = self.qk[index](tokens).view(r, s, 2, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        attention = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(d // self.heads), dim=-1)
        values = tokens.view(r, s, self.heads, -1).transpose(1, 2)
        return RayBlockOutput(tokens + (attention @ values).transpose(1, 2).reshape(r, s, d), attention)

    def weights(self, last):
        return last.ray_attention[:, :, 0].mean(1)

    def readout(self, tokens, last):
        return RayReadout(self.rgb(tokens.mean(1)), self.weights(last))


class UnnormalisedWeights(GoodRay):
    def weights(self, last):
        return torch.sigmoid(last.tokens.mean(-1))


class FixedBlockCount(GoodRay):
    def __init__(self, *, in_dim, num_blocks, heads=2):
        super().__init__(in_dim=in_dim, num_blocks=2, heads=heads)


# ------------------------------------------------------------------------------------------------------------ losses


class RgbLoss(LossSet):
    def __init__(self, weight=1.0):
        super().__init__()
        self.weight = weight

    def forward(self, inputs):
        return {"rgb": self.weight * (inputs.coarse.rgb - inputs.target_rgb).square().mean(), **self.extra(inputs)}

    def extra(self, inputs):
        return {}


class ReadsLogitsUndeclared(RgbLoss):
    def extra(self, inputs):
        return {"ce": F.cross_entropy(inputs.logits, inputs.labels, ignore_index=inputs.ignore_index)}


class SamplesWithoutSemantics(RgbLoss):
    needs_sample_semantics = True


class DeclaresUnusedSemantics(RgbLoss):
    needs_semantics = True


class DetachedTerm(RgbLoss):
    def extra(self, inputs):
        return {"depth": (inputs.coarse.depth.detach() - inputs.target_depth).abs().mean()}


class NanForOneClass(RgbLoss):
    needs_semantics = True

    def extra(self, inputs):  # entropy over log(K): 0 / 0 for one class
        p = inputs.logits.softmax(dim=1)
        return {"entropy": -(p * p.log()).sum(1).mean() / math.log(inputs.logits.shape[1])}


class VectorTerm(RgbLoss):
    def extra(self, inputs):
        return {"per_ray": (inputs.coarse.rgb - inputs.target_rgb).square().mean(-1)}


# --------------------------------------------------------------------------------------- view selectors, datasets


class NearestFirst(ViewSelector):
    def select(self, target_c2w, candidate_c2w, num_views, generator=None):
        distance = (candidate_c2w[:, :3, 3] - target_c2w[:3, 3]).norm(dim=-1)
        order = torch.sort(distance, stable=True).indices
        if generator is not None:
            order = order[torch.randperm(len(order), generator=generator)]
        return order[:num_views].tolist()


class GlobalRandom(NearestFirst):
    def select(self, target_c2w, candidate_c2w, num_views, generator=None):
        return torch.randperm(len(candidate_c2w), generator=generator)[:num_views].tolist()


class RepeatsViews(NearestFirst):
    def select(self, target_c2w, candidate_c2w, num_views, generator=None):
        return [0] * num_views


class SweptRecordedDepth(DepthSource):
    def belief(self, rays, sources, features):
        return source_depth_belief(rays, sources, planes=8)


class UnnormalisedBelief(SweptRecordedDepth):
    def belief(self, rays, sources, features):
        found = super().belief(rays, sources, features)
        return DepthBelief(found.depths, found.probabilities * 2, found.evidence)


class GuessesUnseenRays(SweptRecordedDepth):
    def belief(self, rays, sources, features):
        found = super().belief(rays, sources, features)
        middle = torch.zeros_like(found.probabilities)
        middle[:, found.depths.shape[1] // 2] = 1.0  # where the views tell nothing: the middle of the ray
        return DepthBelief(found.depths, torch.where(found.evidence[:, None], found.probabilities, middle),
                           found.evidence)


class BeliefWithGradient(SweptRecordedDepth):
    def belief(self, rays, sources, features):
        found = super().belief(rays, sources, features)
        scale = features.radiance.mean() * 0 + 1  # keeps the features' graph
        return DepthBelief(found.depths, found.probabilities * scale, found.evidence)


class RandomBelief(SweptRecordedDepth):
    def belief(self, rays, sources, features):
        found = super().belief(rays, sources, features)
        return DepthBelief(found.depths, torch.softmax(torch.rand(found.probabilities.shape), -1), found.evidence)


class Classes(SceneDataset):
    ignore = 255

    class_names = ("wall", "floor", "chair")
    ignore_index = property(lambda self: self.ignore)

    def scenes(self, split):
        return ()

    def load_scene(self, name):
        raise KeyError(name)


class IgnoreIsAClass(Classes):
    ignore = 1


# ------------------------------------------------------------------------------------- every kind, good and broken

WIDTH = config("under_test", width=(int, 8))
HEADS = config("under_test", heads=(int, 2))
WEIGHT = config("under_test", weight=(float, 1.0))


GOOD = [
    ("head", GoodHead, None),
    ("feature_extractor", GoodExtractor, WIDTH),
    ("field_aggregator", GoodField, WIDTH),
    ("ray_aggregator", GoodRay, HEADS),
    ("loss", RgbLoss, WEIGHT),
    ("view_selector", NearestFirst, None),
    ("dataset", Classes, None),
    ("depth_source", SweptRecordedDepth, None),
]

BROKEN = [
    ("feature_extractor", LyingRadianceWidth, WIDTH, "output shapes",
     "radiance map [1, 8, 8, 12] for images [1, 3, 32, 48], expected [1, 9, h, w] (radiance_dim=9)"),
    ("feature_extractor", UnevenLevels, WIDTH, "properties",
     "semantic_dim=16 is not divisible into semantic_levels=3"),
    ("feature_extractor", CrashesOnOtherSizes, WIDTH, "other image sizes",
     "images [1, 3, 40, 36]) raised RuntimeError"),
    ("field_aggregator", SoftmaxOverChannels, WIDTH, "view attention",
     "block 0 view_attention (softmax over views V) [5, 7, 3, 8] sums to"),
    ("ray_aggregator", UnnormalisedWeights, HEADS, "readout", "readout weights [5, 7] sums to"),
    ("ray_aggregator", FixedBlockCount, HEADS, "properties",
     "num_blocks is 2 for a ray aggregator built with num_blocks=3"),
    ("loss", ReadsLogitsUndeclared, WEIGHT, "flags",
     "must be Tensor, not NoneType; a loss set that reads what its flags leave out (None) must set needs_semantics"),
    ("loss", SamplesWithoutSemantics, WEIGHT, "flags", "needs_sample_semantics is True but needs_semantics is False"),
    ("loss", DeclaresUnusedSemantics, WEIGHT, "flags",
     "needs_semantics is True but no term's gradient reaches the logits"),
    ("loss", DetachedTerm, WEIGHT, "gradients", "term 'depth' does not require grad"),
    ("loss", NanForOneClass, WEIGHT, "degenerate inputs",
     "entropy is nan from loss(inputs without sample_semantic, one class)"),
    ("loss", VectorTerm, WEIGHT, "terms", "term 'per_ray' is [6], expected a float scalar tensor []"),
    ("view_selector", GlobalRandom, None, "determinism", "select(..., generator=None) returned"),
    ("view_selector", RepeatsViews, None, "selection",
     "num_views=3, generator=None) returned [0, 0, 0], which repeats a view"),
    ("dataset", IgnoreIsAClass, None, "classes", "ignore_index 1 is a valid class id in [0, 3); it must not be one"),
    ("depth_source", UnnormalisedBelief, None, "belief", "probabilities [5, 8] sums to 2"),
    ("depth_source", GuessesUnseenRays, None, "unseen rays", "are not flat for rays no view sees"),
    ("depth_source", BeliefWithGradient, None, "no gradient", "probabilities requires grad"),
    ("depth_source", RandomBelief, None, "determinism", "differs between two calls on the same inputs"),
]


@pytest.mark.parametrize("kind, factory, schema", GOOD, ids=[row[1].__name__ for row in GOOD])
def test_correct_components_pass_every_check(kind, factory, schema):
    assert failures(kind, factory, schema) == {}


@pytest.mark.parametrize("kind, factory, schema, check, words", BROKEN, ids=[row[1].__name__ for row in BROKEN])
def test_each_broken_component_fails_its_check(kind, factory, schema, check, words):
    found = failures(kind, factory, schema)
    assert check in found and words in found[check], found


def test_a_dataset_that_needs_files_skips_its_class_check():
    def needs_files():
        raise ConfigError("dataset.root is empty")

    results = check_plugin(plugin("dataset", ("files", needs_files, config("files"))), raise_on_failure=False)
    assert {r.check: r.outcome for r in results} == {"classes": "skipped", "config round trip": "passed"}


# ---------------------------------------------------------------------------------------------- targets and pytest


def test_the_kit_passes_the_pipelines_runtime_arguments():
    """A model family's ``parts`` are made per check (with and without a head); every other kind's are fixed."""
    fixed = {kind: tuple(RUNTIME[kind]) for kind in KINDS if kind != "model"}
    assert fixed == {k: v.runtime_arguments for k, v in KINDS.items() if k != "model"}
    assert KINDS["model"].runtime_arguments == ("parts",) and RUNTIME["model"] == {}
    assert set(CHECKS) == set(KINDS)


def test_an_unknown_target_says_what_was_looked_for():
    with pytest.raises(LookupError, match="no entry point in group 'gpnerf', installed distribution or importable "
                                          "module named 'gpnerf_head_nope'"):
        plugin_checks("gpnerf_head_nope")


def write_distribution(root, version="1.2.3"):
    """An installed-looking distribution ``kit-fake-dist`` with entry point ``kit_fake_dist`` (a RgbLoss plugin)."""
    package = root / "kit_fake_dist"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "plugin.py").write_text(textwrap.dedent("""
        from dataclasses import dataclass
        from gpnerf_core import ComponentSpec, LossSet, hookimpl

        @dataclass
        class Config:
            name: str = "fake_rgb"

        class Rgb(LossSet):
            def forward(self, inputs):
                return {"rgb": (inputs.coarse.rgb - inputs.target_rgb).square().mean()}

        @hookimpl
        def gpnerf_register_losses():
            return [ComponentSpec("fake_rgb", Rgb, Config)]
    """))
    info = root / f"kit_fake_dist-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: kit-fake-dist\nVersion: {version}\n")
    (info / "entry_points.txt").write_text("[gpnerf]\nkit_fake_dist = kit_fake_dist.plugin\n")
    (info / "top_level.txt").write_text("kit_fake_dist\n")


@pytest.mark.parametrize("target", ["kit_fake_dist", "kit-fake-dist", "Kit_Fake.Dist", "kit_fake_dist.plugin"])
def test_targets_by_entry_point_distribution_or_module_name(tmp_path, monkeypatch, target):
    write_distribution(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    results = check_plugin(target)
    assert {r.component for r in results} == {"loss/fake_rgb"}
    assert {r.plugin for r in results} == {"kit_fake_dist 1.2.3" if "plugin" not in target else
                                           "kit_fake_dist.plugin 1.2.3"}


def test_pytest_plugin_makes_one_item_per_component_and_check(pytester):
    pytester.makepyfile(kit_bad_plugin=textwrap.dedent("""
        from dataclasses import dataclass
        import torch
        from gpnerf_core import ComponentSpec, PerceptionHead, hookimpl
        from gpnerf_core.types import HeadOutput

        @dataclass
        class Config:
            name: str = "bad"

        class Bad(PerceptionHead):
            def __init__(self, *, in_dim, in_levels, num_outputs):
                super().__init__()
                self.k, self.conv = num_outputs, torch.nn.Conv2d(in_dim, num_outputs, 1)

            num_outputs = property(lambda self: self.k)

            def forward(self, features, output_size):
                return HeadOutput(self.conv(features))  # never resized

        @hookimpl
        def gpnerf_register_heads():
            return [ComponentSpec("bad", Bad, Config)]
    """))
    pytester.makepyfile(test_bad=textwrap.dedent("""
        from gpnerf_core.testing import contract_checks

        pytest_plugins = ["gpnerf_core.testing.pytest_plugin"]

        @contract_checks("kit_bad_plugin")
        def test_contract(gpnerf_check):
            gpnerf_check.run()

        def test_forgotten_decorator(gpnerf_check):
            gpnerf_check.run()
    """))
    pytester.syspathinsert()
    result = pytester.runpytest_inprocess("-q", "-p", "no:cacheprovider", "--collect-only")
    items = [line for line in result.outlines if "test_contract[" in line]
    assert len(items) == len(CHECKS["head"]) and "test_bad.py::test_contract[head/bad: output size]" in items
    result = pytester.runpytest_inprocess("-q", "-p", "no:cacheprovider", "-W", "error::pytest.PytestWarning")
    result.assert_outcomes(passed=len(CHECKS["head"]) - 1, failed=1, errors=1)
    assert "test_forgotten_decorator takes gpnerf_check but is not decorated" in result.stdout.str()
    assert "check 'output size' failed: logits [2, 51, 7, 9], expected [2, 51, 37, 45]" in result.stdout.str()


# ---- stress cases ----------------------------------------------------------------------------------------------------


def stress_plugin(*cases):
    module = types.ModuleType(f"stress_plugin_{'_'.join(c.name for c in cases)}")

    @hookimpl
    def gpnerf_register_stress_cases():
        return list(cases)

    module.gpnerf_register_stress_cases = gpnerf_register_stress_cases
    return module


class GoodCase(StressCase):
    name = "good_case"
    levels = (0.1, 0.5)

    def perturb_sources(self, level, sources, generator):
        noise = torch.rand(sources.rgb.shape, generator=generator) * level
        return replace(sources, rgb=(sources.rgb + noise).clamp(0, 1))


class InPlace(GoodCase):
    name = "in_place"

    def perturb_sources(self, level, sources, generator):
        sources.rgb.mul_(0.5)
        return sources


class GlobalRandom(GoodCase):
    name = "global_random"

    def perturb_sources(self, level, sources, generator):
        return replace(sources, rgb=(sources.rgb + torch.rand(sources.rgb.shape) * level).clamp(0, 1))


class ScaledPoses(GoodCase):
    name = "scaled_poses"

    def perturb_sources(self, level, sources, generator):
        c2w = sources.c2w.clone()
        c2w[:, :3, :3] *= 1 + level
        return replace(sources, c2w=c2w)


class TakesTheTarget(GoodCase):
    name = "takes_the_target"

    def source_indices(self, level, scene, target, num_views, choose):
        return [target, *choose(scene, target, num_views - 1)]


class ScoresATrainingFrame(GoodCase):
    name = "scores_a_training_frame"

    def target_frames(self, level, scene, eval_frames):
        return [*eval_frames, scene.train_frames[0]]


class OutOfRange(GoodCase):
    name = "out_of_range"

    def perturb_sources(self, level, sources, generator):
        return replace(sources, rgb=sources.rgb * 2)


def test_a_correct_stress_case_passes_every_check():
    results = check_plugin(stress_plugin(GoodCase()))
    assert [r.check for r in results] == ["levels", "sources", "targets", "perturbation", "determinism"]
    assert all(r.component == "stress_case/good_case" for r in results)


@pytest.mark.parametrize("case, check, words", [
    (InPlace(), "perturbation", "changed its input in place"),
    (GlobalRandom(), "determinism", "draw randomness from the generator argument only"),
    (ScaledPoses(), "perturbation", "is not a rigid camera-to-world pose"),
    (TakesTheTarget(), "sources", "never the target"),
    (ScoresATrainingFrame(), "targets", "expected distinct held-out frames"),
    (OutOfRange(), "perturbation", "expected [0, 1]"),
])
def test_each_broken_stress_case_fails_its_check(case, check, words):
    results = check_plugin(stress_plugin(case), raise_on_failure=False)
    failed = {r.check: r.message for r in results if r.failed}
    assert list(failed) == [check] and words in failed[check]
    assert failed[check].startswith(f"stress_case {case.name!r} (plugin stress_plugin_{case.name}")


# ------------------------------------------------------------------------------------------------------- model families


def test_a_family_that_silently_ignores_a_configured_head_fails_its_build_check():
    import model_family

    @dataclasses.dataclass
    class IgnoresHeadConfig(model_family.PooledViewsConfig):
        name: str = "ignores_head"

    class IgnoresHead(model_family.PooledViews):
        capabilities = Capabilities(accepts_head=True)  # says it decodes with a head, and never builds one

    def build(*, parts, coarse_samples=8, fine_samples=0, hidden=8, label_rendering=True):
        return IgnoresHead(extractor=parts.build("feature_extractor"), num_classes=parts.num_classes,
                           coarse_samples=coarse_samples, fine_samples=fine_samples, hidden=hidden)

    found = failures("model", build, IgnoresHeadConfig, name="ignores_head")
    assert "a head was configured (+head=unet) but the family built none" in found["build"]
