"""Issue 55: a per-scene model (``Capabilities.generalizable`` False) pointed by a command at data without the scene it
was fitted on is refused in one line naming that scene and the one asked (``engine.fitted_data``), instead of failing
over a missing ``layout_00/`` folder or options inherited from its checkpoint; ``finetune`` opts out."""

from __future__ import annotations

import pytest

from capture_fixtures import write_capture
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.trained import load_trained
from gpnerf_plugins.datasets.embedded.dataset import EmbeddedScenes
from pipeline_check import TINY_SCENES, in_process

SPLATS = ["+experiment=baselines/semantic_3dgs", *TINY_SCENES, "dataset.scenes=[layout_00]", "model.init_points=300",
          "model.feature_dim=4", "model.sh_degree=1", "train.steps=2", "threads=1", "eval.save_images=0"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A 2-step semantic_3dgs fit of embedded ``layout_00`` (its own scene cache) and a capture of another layout."""
    work = tmp_path_factory.mktemp("fitted")
    data = f"dataset.root={work / 'scenes'}"
    assert in_process("run", *SPLATS, data, f"out_dir={work / 'run'}") == 0
    other = EmbeddedScenes(root=str(work / "scenes2"), num_train_scenes=2, num_unseen_scenes=0, frames_per_scene=6,
                           height=32, width=48, eval_every=3)
    capture = write_capture(other.load_scene("layout_01"), work / "kitchen")
    return work, data, load_trained(next((work / "run" / "checkpoints").glob("*.pt"))), capture


def test_its_own_scene_opens_and_names_it(fitted):
    work, data, trained, _ = fitted
    opened = open_trained(trained, [data], command="export")
    assert opened.fitted is not None and opened.fitted.scenes == ("layout_00",)


def test_another_scene_of_the_same_dataset_is_refused_naming_both(fitted):
    work, data, trained, _ = fitted
    other = [data, "dataset.num_train_scenes=2", "dataset.scenes=[layout_01]"]
    with pytest.raises(ConfigError, match=r"^render: model 'semantic_3dgs' was fitted on scene 'layout_00' alone .* "
                                          r"asked for 'layout_01': dataset=embedded .* holds 'layout_01', not "
                                          r"'layout_00'; expected the data it was fitted on"):
        open_trained(trained, other, command="render")
    opened = open_trained(trained, other, command="finetune", other_data=True)  # fits on new scenes by design
    assert opened.fitted.scenes == ("layout_00",)


def test_another_capture_is_refused_naming_the_fitted_scene_in_one_line(fitted, capsys):
    work, _, trained, capture = fitted
    asked = ["dataset=capture", f"dataset.root={capture}", "dataset.height=32", "dataset.width=48"]
    with pytest.raises(ConfigError, match=r"^label: model 'semantic_3dgs' was fitted on scene 'layout_00' alone .* "
                                          r"it was fitted on dataset=embedded, asked for a scene of dataset=capture"):
        open_trained(trained, asked, command="label")
    code = in_process("export", f"checkpoint={trained.path}", *asked, f"out_dir={work / 'refused'}")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len([line for line in err if line.startswith("error:")]) == 1
    assert "fitted on scene 'layout_00'" in err[-1] and "missing" not in err[-1]
    assert not (work / "refused").exists()


def test_another_seed_of_a_generated_dataset_is_refused_naming_the_key(fitted):
    work, data, trained, _ = fitted
    with pytest.raises(ConfigError) as refused:  # dataset.seed=3 generates another room called layout_00
        open_trained(trained, [data, "dataset.seed=3"], command="export")
    message = str(refused.value)
    assert "fitted with dataset.seed=0, and dataset.seed=3 makes other scenes under the same names" in message
    assert "'layout_00'" in message and "\n" not in message
