"""The model-family contract stays small and says what a family is in one place: ``ModelFamily`` has at most twelve
members besides ``capabilities`` and ``hooks``, and a capability is declared if and only if it is implemented."""

import dataclasses
import inspect

import pytest
from gpnerf_core import Capabilities, FamilyHooks, ModelFamily
from gpnerf_core.interfaces.model import OPTIONAL_MEMBERS, capability_problems
from gpnerf_core.registry.components import get_registry

MAX_MEMBERS = 12


def test_model_family_has_at_most_twelve_members_besides_its_capabilities_and_hooks():
    own = {name for name in vars(ModelFamily) if not name.startswith("_")}  # what it defines, nn.Module's aside
    members = own - {"capabilities", "hooks"}
    assert len(members) <= MAX_MEMBERS, sorted(members)
    assert {"semantic_output", "parameter_groups", "forward", "predict"} <= members


def test_every_optional_capability_names_a_member_that_exists_where_it_says():
    flags = {field.name for field in dataclasses.fields(Capabilities)}
    for capability, (owner, member) in OPTIONAL_MEMBERS.items():
        assert capability in flags
        assert hasattr(FamilyHooks if owner == "hooks" else ModelFamily, member), (capability, member)


class Minimal(ModelFamily):
    capabilities = Capabilities(generalizable=False, source_encoding=None)
    semantic_output = None

    def parameter_groups(self):
        return {}

    def forward(self, batch, *, semantics, sample_semantics=False):
        raise NotImplementedError

    def predict(self, camera, sources, *, stride, chunk_rays, features=None):
        raise NotImplementedError


def test_a_capability_declared_but_not_implemented_and_one_implemented_but_not_declared_are_both_named():
    class ClaimsGaussians(Minimal):
        capabilities = Capabilities(generalizable=False, source_encoding=None, gaussians=True)

    class HiddenTeacher(Minimal):
        def teacher_logits(self, image):
            return None

    class TermsWithoutHooks(Minimal):
        capabilities = Capabilities(generalizable=False, source_encoding=None, loss_terms=("smooth",))

    assert capability_problems(Minimal) == []
    assert any("gaussians" in p and "scene_gaussians" in p for p in capability_problems(ClaimsGaussians))
    assert any("teacher_logits" in p for p in capability_problems(HiddenTeacher))
    assert any("loss_terms" in p for p in capability_problems(TermsWithoutHooks))


@pytest.mark.parametrize("name", sorted(get_registry().components["model"]))
def test_every_built_in_family_declares_exactly_what_it_implements(name):
    factory = get_registry().components["model"][name].spec.factory
    family = inspect.signature(factory).return_annotation
    if isinstance(family, str):
        family = factory.__globals__.get(family)
    assert inspect.isclass(family) and issubclass(family, ModelFamily), f"{name}'s factory names no family class"
    assert capability_problems(family) == []


def test_the_files_that_branch_on_the_head_kind_are_the_ones_architecture_md_lists():
    import ast
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    package = root / "gpnerf_core"
    branching = set()
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "Predicts":
                branching.add(path.relative_to(package).as_posix())
    row = next(line for line in (root / "docs" / "architecture.md").read_text().splitlines()
               if line.startswith("| a head kind"))
    listed = set(re.findall(r"`([\w/]+\.py)`", row)) - {"interfaces/head.py", "tests/test_family_contract.py"}
    count = int(re.search(r"the (\d+) files that branch on it", row).group(1))
    assert branching - {"interfaces/head.py"} == listed and count == len(listed)
