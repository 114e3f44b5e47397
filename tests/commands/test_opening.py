"""One way to open a trained model (``engine.opening.open_trained``): the checkpoint's settings restored, the config
validated once per command and process, the chosen weights loaded; every command and tool opens it so."""

import pickle

import pytest
import torch

from gpnerf_core.config.compose import compose
from gpnerf_core.engine import setup
from gpnerf_core.engine.launching import Handover
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.trained import load_trained
from gpnerf_core.tools.viewer.timing import measure
from pipeline_check import TINY_MODEL, TINY_SCENES, in_process, make_trainer


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny run's checkpoint that kept a weight average, written without overrides (as by a run whose defaults
    have changed since: composing its overrides today gives another model; only restoring its settings gives its)."""
    folder = tmp_path_factory.mktemp("opening")
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={folder / 'scenes'}",
                   "train.ema_decay=0.5", f"out_dir={folder / 'run'}"])
    make_trainer(cfg, folder / "run").fit(progress=False)
    return folder, folder / "run" / "checkpoints" / "step_0000002.pt"


@pytest.fixture
def validations(monkeypatch):
    """Counts the configs validated (``validate_config``, which every validation goes through)."""
    counted = []
    validate = setup.validate_config
    monkeypatch.setattr(setup, "validate_config", lambda cfg: counted.append(1) or validate(cfg))
    return counted


def scenes(folder):
    return [*TINY_SCENES, f"dataset.root={folder / 'scenes'}"]


def test_open_trained_restores_validates_once_and_loads_the_chosen_weights(trained, validations):
    folder, checkpoint = trained
    read = load_trained(checkpoint)
    opened = open_trained(read, [*scenes(folder), "model.fine_samples=3"], command="eval")
    assert validations == [1]
    assert opened.trained is read and opened.weights == "average"  # eval.weights' default
    cfg = opened.cfg
    assert cfg.model.field_aggregator.width == 16 and cfg.model.coarse_samples == 6  # restored from the checkpoint
    assert cfg.model.fine_samples == 3  # the command set it: its value stays
    assert any("kept the checkpoint's value of" in note and "field_aggregator.width" in note for note in opened.notes)
    average = read.state["weight_average"]["weights"]
    assert all(torch.equal(v, average[k]) for k, v in opened.components.model.state_dict().items())
    assert opened.device == torch.device("cpu") and opened.fitted is None and opened.reinitialised == []

    last = open_trained(read, scenes(folder), command="eval", weights="trained")
    assert last.weights == "trained"
    assert all(torch.equal(v, read.state["model"][k]) for k, v in last.components.model.state_dict().items())


def test_open_trained_refuses_another_family_and_a_bad_value_naming_the_key(trained):
    folder, checkpoint = trained
    read = load_trained(checkpoint)
    with pytest.raises(ConfigError, match=r"^model=semantic_nerf: checkpoint .* holds a trained model 'gnt'; stress "
                                          r"takes its model family from the checkpoint: drop model=\.\.\.$"):
        open_trained(read, [*scenes(folder), "model=semantic_nerf"], command="stress")
    with pytest.raises(ConfigError, match=r"^eval.chunk_rays=0: expected an integer >= 1$"):
        open_trained(read, [*scenes(folder), "eval.chunk_rays=0"], command="stress")


def test_the_viewer_timing_opens_the_trained_model_with_its_settings(trained):
    """The timing composed the checkpoint's overrides without restoring its settings: a checkpoint whose defaults
    changed since was timed as another model (here: refused, its tensors fit no default model)."""
    folder, checkpoint = trained
    result = measure([f"checkpoint={checkpoint}", *scenes(folder), "view.stride=4"], repeats=1)
    parameters = sum(v.numel() for v in load_trained(checkpoint).state["model"].values())
    assert result["parameters"] == parameters and result["image"] == [32, 48]


def test_the_launchers_handover_travels_without_the_checkpoint(trained):
    """A job pickled into another process (submitit) reads the checkpoint there: its tensors are not in the pickle."""
    _, checkpoint = trained
    read = load_trained(checkpoint)
    handover = pickle.loads(pickle.dumps(Handover(True, read)))
    assert handover == Handover(True, None) and len(pickle.dumps(Handover(True, read))) < 200


def test_eval_and_finetune_validate_their_config_once(trained, validations, tmp_path):
    folder, checkpoint = trained
    common = [f"checkpoint={checkpoint}", *scenes(folder), "eval.save_images=0", "eval.max_views_per_scene=1"]
    assert in_process("eval", *common, f"out_dir={tmp_path / 'eval'}") == 0
    assert len(validations) == 1
    assert in_process("finetune", *common, "dataset.scenes=[unseen_00]", "train.steps=1",
                      f"out_dir={tmp_path / 'finetune'}") == 0
    assert len(validations) == 2


def test_run_validates_once_and_each_job_of_a_sweep_once(trained, validations, tmp_path):
    folder, _ = trained
    tiny = ["+head=unet", "+loss=dgs", *TINY_MODEL, *scenes(folder), "train.steps=1", "eval.splits=[]"]
    assert in_process("run", *tiny, f"out_dir={tmp_path / 'run'}") == 0
    assert len(validations) == 1
    assert in_process("run", "-m", *tiny, "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}") == 0
    assert len(validations) == 3  # a sweep is not prechecked: each job validates its own config


def test_an_experiment_of_another_family_is_refused_over_the_family_first(tmp_path, capsys):
    """Issue 55: a GNT checkpoint's +loss clashed with the experiment's loss, so eval and finetune were refused over a
    +loss=ce the user never typed; the experiment's family is now checked against the checkpoint's first."""
    tiny = [*TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}"]
    assert in_process("run", "+loss=rgb", *tiny, "train.steps=1", "eval.splits=[]", f"out_dir={tmp_path / 'run'}") == 0
    checkpoint = tmp_path / "run" / "checkpoints" / "step_0000001.pt"
    capsys.readouterr()
    for command in ("eval", "finetune"):
        assert in_process(command, f"checkpoint={checkpoint}", "+experiment=baselines/neuray",
                          f"out_dir={tmp_path / command}") == 2
        err = capsys.readouterr().err
        assert (f"error: +experiment=baselines/neuray: the experiment trains model 'neuray', but checkpoint "
                f"{checkpoint} is a gnt model; {command} takes its model family from the checkpoint: drop "
                f"+experiment=baselines/neuray, or train a neuray model first") in err, err
        assert "+loss" not in err and not (tmp_path / command).exists()
