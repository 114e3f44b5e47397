"""Turns plugins into checks (one per component and rule), runs them and reports each failure in one line."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

from gpnerf_core.registry.kinds import PART_KINDS
from gpnerf_core.registry.plugins import PluginInfo, PluginProblem
from gpnerf_core.testing.checks import CHECKS, RUNTIME, CheckFailed, CheckSkipped, Subject
from gpnerf_core.testing.checks.common import component_label
from gpnerf_core.testing.checks.stress import CHECKS as STRESS_CHECKS
from gpnerf_core.testing.target import Target, load_targets

PASSED, FAILED, SKIPPED = "passed", "failed", "skipped"


@dataclass(frozen=True)
class CheckResult:
    """The outcome of one check of one component.

    Attributes:
        component: ``kind/name`` (``head/fancy``), or ``plugin`` for a plugin that did not load at all.
        plugin: the provider and its version (``gpnerf_head_fancy 0.1.0``).
        check: the check's name (``output size``).
        outcome: ``passed``, ``failed`` or ``skipped``.
        message: for a failure or a skip, one line naming the component, the check and the shapes involved.
    """

    component: str
    plugin: str
    check: str
    outcome: str
    message: str = ""

    @property
    def failed(self) -> bool:
        return self.outcome == FAILED


class ContractError(AssertionError):
    """Raised when checks fail: one line per failure; ``results`` holds the failed ``CheckResult``s."""

    def __init__(self, results: Sequence[CheckResult]) -> None:
        self.results = list(results)
        super().__init__("\n".join(result.message for result in self.results))


@dataclass(frozen=True)
class Check:
    """One rule applied to one component; ``str(check)`` is its test id (``head/fancy: output size``)."""

    component: str
    plugin: str
    name: str
    label: str
    function: Callable[[], None]

    def __str__(self) -> str:
        return f"{self.component}: {self.name}"

    def result(self) -> CheckResult:
        """Run the check and return its outcome (never raises for a failing component)."""
        try:
            self.function()
        except CheckFailed as failure:
            return self._outcome(FAILED, f"{self.label}: check {self.name!r} failed: {failure}")
        except CheckSkipped as skip:
            return self._outcome(SKIPPED, f"{self.label}: check {self.name!r} skipped: {skip}")
        return self._outcome(PASSED)

    def run(self) -> CheckResult:
        """Run the check; raise ``ContractError`` if it fails, else return the (passed or skipped) result."""
        outcome = self.result()
        if outcome.failed:
            raise ContractError([outcome])
        return outcome

    def _outcome(self, outcome: str, message: str = "") -> CheckResult:
        return CheckResult(self.component, self.plugin, self.name, outcome, message)


def plugin_checks(
    targets: Target | Sequence[Target], *, configs: Mapping[str, Mapping[str, Any]] | None = None
) -> list[Check]:
    """Every check of every component the target plugins register, plus one failing check per registration problem.

    Args:
        targets: an entry-point name, a distribution name, a plugin module or a module path, or a list of them.
        configs: ``{"kind/name": {field: value}}`` config fields that replace the dataclass defaults for the checks
            (e.g. small widths; a model family's parts are built with the configs given here for them, and the family's
            own config may choose and set its parts: ``{"model/mine": {"feature_extractor": {"name": ..., ...}}}``);
            every key must name one of the targets' components (unless the targets had
            registration problems: then their failing "registration" checks are the report, not a KeyError).
    """
    loaded = load_targets(targets)
    checks = [_problem_check(problem) for problem in loaded.problems]
    if not loaded.components and not loaded.problems and not loaded.stress_cases:
        checks.append(_problem_check(PluginProblem(PluginInfo(", ".join(loaded.plugins)), "registers no components")))
    configs = dict(configs or {})
    keys = {f"{entry.kind}/{entry.spec.name}" for entry in loaded.components}
    unknown = sorted(set(configs) - keys)
    if unknown and not loaded.problems:  # with problems, their failing checks say why the component is missing
        raise KeyError(f"configs names {unknown[0]!r}, which is not a component of {', '.join(loaded.plugins)}; "
                       f"its components: {', '.join(sorted(keys)) or 'none'}")
    part_configs = {key: value for key, value in configs.items() if key.split("/")[0] in PART_KINDS}
    for entry in loaded.components:
        key = f"{entry.kind}/{entry.spec.name}"
        subject = Subject(
            entry.kind, entry.spec.name, entry, loaded.registry, configs.get(key, {}), RUNTIME[entry.kind],
            part_configs if entry.kind == "model" else {},
        )
        plugin = f"{entry.provider} {entry.version}"
        for name, function in CHECKS[entry.kind].items():
            checks.append(Check(key, plugin, name, subject.label, functools.partial(function, subject)))
    for case, provider in loaded.stress_cases:
        info = loaded.registry.plugins.get(provider, PluginInfo(provider))
        label = component_label("stress_case", case.name, provider, info.version)
        for name, function in STRESS_CHECKS.items():
            checks.append(Check(f"stress_case/{case.name}", f"{provider} {info.version}", name, label,
                                functools.partial(function, case)))
    return checks


def check_plugin(
    targets: Target | Sequence[Target],
    *,
    configs: Mapping[str, Mapping[str, Any]] | None = None,
    raise_on_failure: bool = True,
) -> list[CheckResult]:
    """Run every check of every component of ``targets`` (see ``plugin_checks``).

    A component that does not build skips its other checks. Raises ``ContractError`` listing every failure unless
    ``raise_on_failure`` is False; returns the results otherwise.
    """
    results: list[CheckResult] = []
    unbuildable: set[str] = set()
    for check in plugin_checks(targets, configs=configs):
        if check.component in unbuildable:
            results.append(check._outcome(SKIPPED, f"{check.label}: check {check.name!r} skipped: it does not build"))
            continue
        result = check.result()
        if result.failed and check.name == "build":
            unbuildable.add(check.component)
        results.append(result)
    failures = [result for result in results if result.failed]
    if failures and raise_on_failure:
        raise ContractError(failures)
    return results


def contract_checks(
    targets: Target | Sequence[Target], *, configs: Mapping[str, Mapping[str, Any]] | None = None
) -> Any:
    """A ``pytest.mark.parametrize`` of the ``gpnerf_check`` fixture (``gpnerf_core.testing.pytest_plugin``) over every
    check of ``targets`` (see ``plugin_checks``); one test item per component and check."""
    import pytest  # only test suites call this

    checks = plugin_checks(targets, configs=configs)
    return pytest.mark.parametrize("gpnerf_check", checks, ids=[str(check) for check in checks], indirect=True)


def _problem_check(problem: PluginProblem) -> Check:
    def fail() -> None:
        raise CheckFailed(problem.reason)

    if problem.component and "/" in problem.component:
        label = component_label(*problem.component.split("/", 1), problem.plugin.name, problem.plugin.version)
    else:
        label = f"plugin {problem.plugin}"
    plugin = f"{problem.plugin.name} {problem.plugin.version}"
    return Check(problem.component or "plugin", plugin, "registration", label, fail)
