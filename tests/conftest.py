import os
from pathlib import Path

import pytest
import torch

# The suite must not pick up third-party plugins installed in the environment.
os.environ.setdefault("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")

TESTS = Path(__file__).resolve().parent
SLOWEST_FILES = (
    "sizing/test_sizing.py", "training/test_distributed.py", "test_docs.py", "commands/test_run.py",
    "commands/test_bench.py", "training/test_slurm.py", "stress/test_stress.py", "training/test_interrupt.py",
    "commands/test_unlabelled.py", "training/test_trainer.py", "commands/test_reliability_tools.py",
    "commands/test_reliability_runs.py", "commands/test_run_eval_curve.py", "commands/test_finetune.py",
    "evaluation/test_instances.py", "commands/test_view.py", "commands/test_plugins.py", "test_reliability_plugins.py",
    "commands/test_model_family.py", "commands/test_baseline_families.py", "commands/test_render.py",
    "plugins/test_capture.py",
)
"""The slowest test files, slowest first (``--durations`` on 2 cores, 2026-12-02 and -03): run before the others, so
that the two xdist workers (``-n 2 --dist loadfile --no-loadscope-reorder`` in pyproject.toml) finish together
instead of one ending on a long file while the other waits."""


def pytest_collection_modifyitems(config, items):
    def rank(item) -> int:
        try:
            name = item.path.resolve().relative_to(TESTS).as_posix()
        except ValueError:
            return len(SLOWEST_FILES)
        return SLOWEST_FILES.index(name) if name in SLOWEST_FILES else len(SLOWEST_FILES)

    items.sort(key=rank)  # stable: each file's tests stay together and in order


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    yield


@pytest.fixture
def one_thread():
    """torch on one thread for the test (as a config's ``threads=1``), restored afterwards: more threads only contend
    on the CI's 2 cores."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
