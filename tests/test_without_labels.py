"""Scenes without labels and datasets without a class list, before any work: training a loss set that reads labels on
them is refused in one line, the head takes a checkpoint's classes where the dataset has none, and checkpoints store
their classes (older ones, without, still load)."""

import pytest
import torch
from omegaconf import OmegaConf, open_dict

from gpnerf_core.model.build import build_components
from gpnerf_core.model.classes import ClassList
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.registry.plugins import BUILTIN_PLUGINS, make_plugin_manager
from gpnerf_core.registry.components import collect
from gpnerf_core.model.checkpoint import read_checkpoint
from gpnerf_core.model.classes import stored_classes
from gpnerf_core.engine.validation import check_data
from gpnerf_plugins.datasets.embedded import CLASS_NAMES, IGNORE_INDEX
from pipeline_check import TINY_MODEL, TINY_SCENES, make_trainer

CHECKPOINT_CLASSES = ClassList(("wall", "floor", "chair"), 255, "checkpoint old.pt", from_checkpoint=True)


pytestmark = pytest.mark.usefixtures("one_thread")  # the configs' threads=1 (open_trained sets it too)


@pytest.fixture(scope="module")
def registry():
    """The built-in plugins and the test dataset ``unlabelled_embedded`` (``tests/unlabelled_scenes.py``)."""
    return collect(make_plugin_manager(builtins=(*BUILTIN_PLUGINS, "unlabelled_scenes"), autoload=False))


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("rooms")


def config(root, *overrides, loss="dgs", **dataset):
    """The tiny model on ``unlabelled_embedded`` (every scene without labels unless ``without_labels`` says)."""
    cfg = compose(["+head=unet", f"+loss={loss}", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root}", *overrides])
    return unlabelled(cfg, **dataset)


def unlabelled(cfg, **dataset):
    """``cfg`` with its embedded dataset node switched to ``unlabelled_embedded`` (with ``dataset`` options)."""
    with open_dict(cfg):
        cfg.dataset = {**OmegaConf.to_container(cfg.dataset), "name": "unlabelled_embedded", **dataset}
    return cfg


@pytest.mark.parametrize("loss", ["ce", "sd", "dgs"])
def test_a_loss_set_that_needs_labels_is_refused_on_a_training_scene_without_labels(registry, root, loss):
    cfg = config(root, loss=loss)
    components = build_components(cfg, registry)
    with pytest.raises(ConfigError) as refused:
        check_data(cfg, components, training=True)
    assert str(refused.value) == (f"scene 'layout_00' has no labels, but loss {loss!r} trains on labels; train without "
                                  "labels with +loss=label_free (colour + distillation from the 2D teacher)")
    check_data(cfg, components, training=False)  # evaluating it is fine: colour and depth are scored


def test_loss_sets_without_labels_and_labelled_training_scenes_are_accepted(registry, root):
    label_free = config(root, loss="label_free")
    check_data(label_free, build_components(label_free, registry), training=True)
    only_unseen = config(root, without_labels=["unseen_00"])  # the scene trained on has labels
    check_data(only_unseen, build_components(only_unseen, registry), training=True)


def test_an_instance_loss_is_refused_for_the_labels_not_the_instance_ids(registry, root):
    cfg = compose(["+head=instance", "+loss=instance", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root}",
                   "head.slots=9"])
    cfg = unlabelled(cfg)
    with pytest.raises(ConfigError, match=r"^scene 'layout_00' has no labels, but loss 'instance' trains on labels"):
        check_data(cfg, build_components(cfg, registry), training=True)
    check_data(cfg, build_components(cfg, registry), training=False)  # rendered only: no instance ids needed


def test_a_dataset_without_a_class_list_takes_the_checkpoints_classes(registry, root):
    cfg = config(root, loss="label_free", class_list=False)
    with pytest.raises(ConfigError, match=r"^dataset 'unlabelled_embedded' has no class list \(class_names is "
                                          r"empty\), so head 'unet' has no classes to predict; "):
        build_components(cfg, registry)
    components = build_components(cfg, registry, classes=CHECKPOINT_CLASSES)
    assert components.classes is CHECKPOINT_CLASSES and components.model.semantic_output.num_outputs == 3
    assert components.model.head.num_outputs == 3
    assert CHECKPOINT_CLASSES.describe() == "3 classes of checkpoint old.pt (wall, floor, chair)"
    own = build_components(config(root, loss="label_free"), registry, classes=CHECKPOINT_CLASSES)
    assert own.classes.names == CLASS_NAMES and not own.classes.from_checkpoint  # a dataset's own list wins


def test_checkpoints_store_their_classes_and_older_ones_still_load(root, tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={root}", "train.steps=1"])
    result = make_trainer(cfg, tmp_path / "run").fit(progress=False)
    state = read_checkpoint(result.checkpoint)
    assert state["class_names"] == list(CLASS_NAMES) and state["ignore_index"] == IGNORE_INDEX
    assert stored_classes(state, result.checkpoint) == (CLASS_NAMES, IGNORE_INDEX)

    old = tmp_path / "old.pt"  # as written before checkpoints kept their classes (and their content hash)
    torch.save({k: v for k, v in state.items() if k not in ("class_names", "ignore_index", "content_sha256")}, old)
    assert stored_classes(read_checkpoint(old), old) is None
    with open_dict(cfg):
        cfg.checkpoint = str(old)
    loaded = open_trained(None, cfg=cfg, command="eval")  # reads cfg.checkpoint, as a job the launcher did not reach
    assert loaded.components.classes.names == CLASS_NAMES and not loaded.components.classes.from_checkpoint
    assert all(torch.equal(v, state["model"][k]) for k, v in loaded.components.model.state_dict().items())
    assert not any("class list" in note for note in loaded.notes)

    with pytest.raises(DataError, match=r"^checkpoint bad.pt: class_names is 'wall'; expected a list of class names$"):
        stored_classes({"class_names": "wall", "ignore_index": 255}, "bad.pt")
    assert stored_classes({"class_names": [], "ignore_index": 255}, "none.pt") is None  # a model without classes
