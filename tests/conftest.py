import os

import pytest
import torch

# The suite must not pick up third-party plugins installed in the environment.
os.environ.setdefault("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "1")


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    yield
