"""Contract kit: checks every component a plugin registers against its interface, from the plugin's own tests.

    from gpnerf_core.testing import check_plugin

    def test_contract():
        check_plugin("gpnerf_head_fancy")  # entry-point, distribution or module name, or the module itself

Each component is built small on the CPU and checked for output shapes and dtypes at several sizes, gradients to every
parameter, train and eval modes, finite outputs on degenerate inputs and a config round trip through Hydra. A
failure raises ``ContractError`` naming the component, its plugin, the check and the shapes. For one test item per
component and check, decorate a test with ``contract_checks`` and enable the pytest plugin
``gpnerf_core.testing.pytest_plugin`` (its docstring shows how).
"""

from gpnerf_core.testing.checks import CHECKS
from gpnerf_core.testing.runner import Check, CheckResult, ContractError, check_plugin, contract_checks, plugin_checks

__all__ = ["CHECKS", "Check", "CheckResult", "ContractError", "check_plugin", "contract_checks", "plugin_checks"]
