"""pytest plugin of the contract kit: one test item per component and check.

Enable it in a test module (or a conftest) and parametrize a test that takes the ``gpnerf_check`` fixture::

    from gpnerf_core.testing import contract_checks

    pytest_plugins = ["gpnerf_core.testing.pytest_plugin"]

    @contract_checks("gpnerf_head_fancy", configs={"head/fancy": {"hidden": 8}})
    def test_contract(gpnerf_check):
        gpnerf_check.run()

``contract_checks`` takes ``plugin_checks``'s arguments; import it from ``gpnerf_core.testing``, not from this module
(pytest must import a plugin before anyone else does). Items are named ``test_contract[head/fancy: output size]``; a
check that cannot run here (a dataset without its files) is reported as skipped.
"""

from __future__ import annotations

import pytest

from gpnerf_core.testing.runner import Check, CheckResult


class PytestCheck:
    """The ``gpnerf_check`` fixture's value: a ``Check`` whose ``run`` turns a skipped check into a pytest skip."""

    def __init__(self, check: Check) -> None:
        self.check = check

    def run(self) -> CheckResult:
        """Run the check: raises ``ContractError`` when it fails, skips the test when it cannot run here."""
        result = self.check.run()
        if result.outcome == "skipped":
            pytest.skip(result.message)
        return result


@pytest.fixture
def gpnerf_check(request: pytest.FixtureRequest) -> PytestCheck:
    """One contract check, from ``@contract_checks(...)`` on the test."""
    check = getattr(request, "param", None)
    if not isinstance(check, Check):
        raise pytest.UsageError(
            f"{request.node.nodeid} takes gpnerf_check but is not decorated with @contract_checks(...)"
        )
    return PytestCheck(check)
