"""What every command imports before it does anything: the suite starts the command line about 200 times and a user
starts it for each command, so libraries only some paths use (SciPy's optimizer and image filters, scikit-image's
metrics and readers, matplotlib's figures) are imported where they are used (docs/benchmarks.md, the test suite)."""

import json
import subprocess
import sys

DEFERRED = ("scipy.optimize", "scipy.ndimage", "scipy.stats", "skimage.metrics", "skimage.io", "skimage.transform",
            "matplotlib.figure")

LOADED_BY_A_COMMAND = """
import json, sys
import gpnerf_core.cli
import gpnerf_core.engine.launching, gpnerf_core.engine.opening, gpnerf_core.evaluation.evaluator  # what `run` imports
from gpnerf_core.commands import eval, export, finetune, render, run, view
from gpnerf_core.registry.components import get_registry
get_registry()  # every built-in plugin imported, as a command does before it builds anything
print(json.dumps(sorted(sys.modules)))
"""


def test_a_command_and_every_built_in_plugin_load_without_the_deferred_libraries(tmp_path):
    env = {"GPNERF_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", LOADED_BY_A_COMMAND], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    loaded = set(json.loads(done.stdout.strip().splitlines()[-1]))
    users = ("gpnerf_core.evaluation.instances", "gpnerf_core.evaluation.metrics", "gpnerf_core.evaluation.visualize",
             "gpnerf_plugins.datasets.common.image_io", "gpnerf_plugins.datasets.capture.video_frames")
    assert [name for name in users if name not in loaded] == []  # the modules that use them are loaded
    assert [name for name in DEFERRED if name in loaded] == []
