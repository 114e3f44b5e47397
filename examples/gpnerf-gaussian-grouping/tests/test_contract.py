"""The contract kit passes the family, and fails each broken variant of it naming what broke."""

import dataclasses
import types

import torch

from gpnerf_core import ComponentSpec, hookimpl
from gpnerf_core.testing import check_plugin, contract_checks
from gpnerf_gaussian_grouping.config import GaussianGroupingConfig
from gpnerf_gaussian_grouping.model import GaussianGrouping, GroupingHooks
from gpnerf_gaussian_grouping.plugin import build_gaussian_grouping

pytest_plugins = ["gpnerf_core.testing.pytest_plugin"]

SMALL = {"model/gaussian_grouping": {"init_points": 200, "identity_dim": 4, "sh_degree": 1, "reg3d_sample_size": 50}}
"""Small; the kit makes its density control act within its steps itself (``KIT_DENSITY``)."""


@contract_checks("gpnerf-gaussian-grouping", configs=SMALL)  # the installed distribution, by name
def test_contract(gpnerf_check):
    gpnerf_check.run()


def variant(family: type) -> types.ModuleType:
    """A plugin module registering ``family`` built as the real one is, under the name ``broken_grouping``."""

    @dataclasses.dataclass
    class BrokenConfig(GaussianGroupingConfig):
        name: str = "broken_grouping"

    def build(**options):
        built = build_gaussian_grouping(**options)
        broken = family.__new__(family)
        broken.__dict__ = built.__dict__
        return broken

    build.__annotations__["return"] = family  # the docs' pattern: the registry reads the class it builds
    module = types.ModuleType("broken_grouping_plugin")
    module.gpnerf_register_models = hookimpl(lambda: [ComponentSpec("broken_grouping", build, BrokenConfig)])
    return module


def failed(family: type) -> dict[str, str]:
    config = {"model/broken_grouping": SMALL["model/gaussian_grouping"]}
    results = check_plugin(variant(family), configs=config, raise_on_failure=False)
    return {result.check: result.message for result in results if result.failed}


def test_a_term_that_turns_nan_fails_naming_the_term():
    class NaNHooks(GroupingHooks):
        def loss_terms(self, state, wanted):
            terms = dict(super().loss_terms(state, wanted))
            terms["identity_3d"] = terms["identity_3d"] * float("nan")
            return terms

    class NaNTerm(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=NaNHooks)

    assert "loss term 'identity_3d' is nan at step 0" in failed(NaNTerm)["training hooks"]


def test_a_densification_that_skips_the_optimizer_fails():
    class SkipsOptimizer(GroupingHooks):
        def density_control(self, state):
            gaussians = self.family.gaussians
            rows = {name: torch.cat([row.detach(), row.detach()[:1]]) for name, row in gaussians.rows().items()}
            gaussians.set_rows(rows)  # one more Gaussian, the optimizer still holding the old tensors

    class Skips(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=SkipsOptimizer)

    assert "parameters were replaced without the optimizer" in failed(Skips)["training hooks"]


def test_a_family_that_grows_but_says_its_size_does_not_change_fails():
    from gpnerf_core import FamilyHooks

    class SilentHooks(GroupingHooks):
        resize_to = FamilyHooks.resize_to  # nothing declared, nothing implemented: only the growth tells

    class Grows(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, changes_size=False, hooks=SilentHooks)

    assert "changed its shape, but capabilities.changes_size is False" in failed(Grows)["training hooks"]


def test_gaussians_whose_columns_disagree_fail_before_export_would():
    class ShortLabels(GaussianGrouping):
        def scene_gaussians(self, sources, *, near, far, features=None):
            splats = super().scene_gaussians(sources, near=near, far=far, features=features)
            return dataclasses.replace(splats, labels=splats.labels[:-1])

    message = failed(ShortLabels)["training hooks"]
    assert "scene_gaussians: its labels has" in message and "export refuses it" in message


def test_a_gaussian_that_turns_nan_fails_before_a_checkpoint_would_hold_it():
    class NaNHooks(GroupingHooks):
        def callbacks(self):  # its own finiteness check left out, as a family written from scratch might
            return tuple(c for c in super().callbacks() if c.run != self.check_finite)

        def density_control(self, state):
            super().density_control(state)
            if state.step == 3:
                with torch.no_grad():
                    self.family.gaussians.means[0, 0] = float("nan")

    class TurnsNaN(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=NaNHooks)

    message = failed(TurnsNaN)["training hooks"]
    assert "after step 3: parameter 'gaussians.means' holds NaN or Inf" in message


def test_a_densification_that_drops_the_optimizer_state_fails():
    class DropsMoments(GroupingHooks):
        def density_control(self, state):
            super().density_control(state)
            gaussians = self.family.gaussians
            moments = state.optimizer.state.get(gaussians.means, {})
            for key in ("exp_avg", "exp_avg_sq"):  # stale moments of the old size, as a hand-written resize might leave them
                if key in moments:
                    moments[key] = moments[key][:-1].clone()

    class Drops(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=DropsMoments)

    message = failed(Drops)["training hooks"]
    assert "exp_avg" in message and "'gaussians.means'" in message and "did not follow its rows" in message


def test_a_family_that_declares_changes_size_but_never_changes_fails():
    class NeverDensifies(GroupingHooks):
        def density_control(self, state):
            pass  # statistics and densification left out

    class Never(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=NeverDensifies)

    assert "changes_size is True but no parameter changed size" in failed(Never)["training hooks"]


def test_a_checkpoint_that_does_not_reload_fails():
    class KeepsItsSize(GroupingHooks):
        def resize_to(self, weights, source):
            pass  # a checkpoint of another size is not followed

    class NoResize(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, hooks=KeepsItsSize)

    message = failed(NoResize)["training hooks"]
    assert "loading its saved weights into a fresh build" in message and "gaussians." in message


def test_gaussians_whose_labels_are_out_of_range_fail():
    class HighLabels(GaussianGrouping):
        def scene_gaussians(self, sources, *, near, far, features=None):
            splats = super().scene_gaussians(sources, near=near, far=far, features=features)
            return dataclasses.replace(splats, labels=splats.labels.clamp_min(0) + self.slots + 1)

    assert "scene_gaussians: its labels reach" in failed(HighLabels)["training hooks"]


def test_a_capability_it_declares_but_lacks_is_refused_at_registration_naming_the_plugin():
    class ClaimsATeacher(GaussianGrouping):
        capabilities = dataclasses.replace(GaussianGrouping.capabilities, teacher=True)

    message = failed(ClaimsATeacher)["registration"]
    assert "plugin broken_grouping_plugin" in message
    assert ("ClaimsATeacher declares capabilities.teacher but ClaimsATeacher does not implement teacher_logits"
            in message)
