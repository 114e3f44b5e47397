"""``import gpnerf_core`` asks OpenMP for passive waiting before torch loads it, unless told otherwise
(``gpnerf_core.runtime.openmp``)."""

import os
import subprocess
import sys

from gpnerf_core.runtime.openmp import passive_wait

SHOW = "import os, gpnerf_core, torch; print(os.environ.get('OMP_WAIT_POLICY'))"


def test_passive_unless_a_policy_is_set_or_it_is_switched_off():
    environ = {}
    assert passive_wait(environ) and environ == {"OMP_WAIT_POLICY": "PASSIVE"}
    chosen = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert not passive_wait(chosen) and chosen == {"OMP_WAIT_POLICY": "ACTIVE"}
    off = {"GPNERF_OMP_PASSIVE": "0"}
    assert not passive_wait(off) and "OMP_WAIT_POLICY" not in off


def test_importing_gpnerf_core_sets_it_before_torch_loads():
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GPNERF_OMP_PASSIVE")}
    shown = [subprocess.run([sys.executable, "-c", SHOW], env=dict(env, **extra), capture_output=True, text=True,
                            timeout=120).stdout.strip() for extra in ({}, {"GPNERF_OMP_PASSIVE": "0"})]
    assert shown == ["PASSIVE", "None"]
