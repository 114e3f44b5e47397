"""The contract kit's ``labels`` check holds a loss set to its ``needs_labels``: one that says it needs no labels must
give the same terms when every label is the ignore index (a scene without labels)."""

import dataclasses
import types

import torch.nn.functional as F

from gpnerf_core import ComponentSpec, LossSet, hookimpl
from gpnerf_core.testing import check_plugin


@dataclasses.dataclass
class Config:
    name: str = "under_test"


class ColourOnly(LossSet):
    needs_labels = False

    def forward(self, inputs):
        return {"rgb": (inputs.coarse.rgb - inputs.target_rgb).square().mean()}


class Distills(ColourOnly):
    """Colour and a distillation of the rendered features towards the teacher: no label read."""

    needs_semantics = True

    def forward(self, inputs):
        distance = 1.0 - F.cosine_similarity(inputs.coarse.semantic, inputs.teacher_at_rays.detach(), dim=-1).mean()
        return {**super().forward(inputs), "sd": distance}


class ClaimsNoLabelsButReadsThem(Distills):
    def forward(self, inputs):
        ce = F.cross_entropy(inputs.logits, inputs.labels, ignore_index=inputs.ignore_index, reduction="sum")
        return {**super().forward(inputs), "ce": ce / max(int((inputs.labels != inputs.ignore_index).sum()), 1)}


class ClaimsNoLabelsButNeedsInstances(Distills):
    needs_instances = True


class LabelsFlagNotABool(ColourOnly):
    needs_labels = "no"


def labels_check(factory):
    """The ``labels`` check's message for a loss set ``factory`` (None when it passes)."""
    module = types.ModuleType("labels_check_plugin")
    module.gpnerf_register_losses = hookimpl(lambda: [ComponentSpec("under_test", factory, Config)])
    results = {r.check: r for r in check_plugin(module, raise_on_failure=False)}
    if not results["labels"].failed:
        return None
    return results["labels"].message.split("check 'labels' failed: ", 1)[1]


def test_loss_sets_that_read_no_labels_pass():
    assert labels_check(ColourOnly) is None
    assert labels_check(Distills) is None


def test_a_loss_set_that_reads_labels_it_says_it_does_not_need_fails():
    message = labels_check(ClaimsNoLabelsButReadsThem)
    assert message.startswith("needs_labels is False but term 'ce' changes when every label is ignored (")
    assert message.endswith("a loss set that reads labels must set needs_labels = True")


def test_instance_ids_are_labels_and_the_flag_is_a_bool():
    assert labels_check(ClaimsNoLabelsButNeedsInstances) == (
        "needs_labels is False but needs_instances is True; instance ids are labels, so set needs_labels = True")
    assert labels_check(LabelsFlagNotABool) == "needs_labels is 'no', expected a bool"
