import os

import pytest
import torch

# The suite must not pick up third-party plugins installed in the environment.
os.environ.setdefault("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")


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
