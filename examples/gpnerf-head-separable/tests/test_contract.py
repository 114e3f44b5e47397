"""The gpnerf-core contract kit, in both forms: one call, and one test item per component and check."""

from gpnerf_core.testing import check_plugin, contract_checks

pytest_plugins = ["gpnerf_core.testing.pytest_plugin"]

SMALL = {"head/separable": {"channels": 16, "norm_groups": 4}}


@contract_checks("gpnerf-head-separable", configs=SMALL)  # the installed distribution, by name
def test_contract(gpnerf_check):
    gpnerf_check.run()


def test_contract_at_the_default_sizes():
    results = check_plugin("gpnerf_head_separable")  # the entry point; raises ContractError on any failure
    assert {r.component for r in results} == {"head/separable", "loss/dice"}
