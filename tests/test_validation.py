"""Every invalid value is refused before any work, in one line naming the key, the value and what is expected; data a
run cannot train on is refused before training."""

import shutil

import pytest
import torch

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.data import checks
from gpnerf_core.data.checks import check_scene_files
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.types import Frame, Scene
from gpnerf_core.engine.validation import check_data, validate_config
from pipeline_check import TINY_MODEL, TINY_SCENES

BAD_VALUES = [
    ("train.steps=0", "train.steps=0: expected an integer >= 1"),
    ("train.steps=-5", "train.steps=-5: expected an integer >= 1"),
    ("train.rays=0", "train.rays=0: expected an integer >= 1"),
    ("train.rays=-256", "train.rays=-256: expected an integer >= 1"),
    ("train.targets_per_step=0", "train.targets_per_step=0: expected an integer >= 1"),
    ("model.lr.feature_extractor=-0.001", "model.lr.feature_extractor=-0.001: expected a finite learning rate > 0"),
    ("model.lr.transformer=0", "model.lr.transformer=0.0: expected a finite learning rate > 0"),
    ("model.lr.head=inf", "model.lr.head=inf: expected a finite learning rate > 0"),
    ("model.lr.head=nan", "model.lr.head=nan: expected a finite learning rate > 0"),
    ("train.lr_decay_rate=0", "train.lr_decay_rate=0.0: expected a factor in (0, 1]"),
    ("train.lr_decay_rate=1.5", "train.lr_decay_rate=1.5: expected a factor in (0, 1]"),
    ("train.lr_decay_steps=0", "train.lr_decay_steps=0: expected an integer >= 1"),
    ("train.grad_clip=-1", "train.grad_clip=-1.0: expected a finite norm >= 0"),
    ("train.ema_decay=1", "train.ema_decay=1.0: expected a decay in [0, 1)"),
    ("eval.weights=best", "eval.weights='best': expected one of average, trained"),
    ("train.log_every=0", "train.log_every=0: expected an integer >= 1"),
    ("train.checkpoint_every=-10", "train.checkpoint_every=-10: expected an integer >= 0"),
    ("model.coarse_samples=1", "model.coarse_samples=1: expected an integer >= 2"),
    ("model.fine_samples=-1", "model.fine_samples=-1: expected an integer >= 0"),
    ("model.num_source_views=-1", "model.num_source_views=-1: expected an integer >= 0 (0 only for a per-scene family"),
    ("eval.chunk_rays=0", "eval.chunk_rays=0: expected an integer >= 1"),
    ("eval.render_stride=-2", "eval.render_stride=-2: expected an integer >= 0"),
    ("eval.max_views_per_scene=-1", "eval.max_views_per_scene=-1: expected an integer >= 0"),
    ("eval.save_images=-1", "eval.save_images=-1: expected an integer >= 0"),
    ("eval.splits=[train,test]", "eval.splits contains 'test'; expected some of train, unseen"),
    ("seed=-1", "seed=-1: expected an integer in [0, 9223372036854775807]"),
    ("seed=9223372036854775808", "seed=9223372036854775808: expected an integer in [0, 9223372036854775807]"),
    ("threads=-2", "threads=-2: expected an integer in [0, 1024]"),
    ("threads=100000", "threads=100000: expected an integer in [0, 1024]"),
    ("train.keep_checkpoints=-1", "train.keep_checkpoints=-1: expected an integer >= 0"),
    ("device=meta", "device='meta': expected auto, cpu or cuda[:N]"),
    ("train.precision=fp16", "train.precision='fp16': expected one of fp32, bf16"),
    ("train.loggers=[csv,wandb]", "train.loggers contains 'wandb'; known loggers: csv, tensorboard"),
    ("+train.stpes=10", "unknown config key 'train.stpes'; TrainConfig has:"),
    ("+foo=1", "unknown config key 'foo'; RootConfig has:"),
    ("+model.semantic_field.frozen=true", "unknown config key 'model.semantic_field.frozen'; SemanticFieldConfig has:"),
    ("+eval.every=5", "unknown config key 'eval.every'; EvalConfig has:"),
]


@pytest.mark.parametrize("override, message", BAD_VALUES, ids=[o for o, _ in BAD_VALUES])
def test_bad_value_is_refused_in_one_line(override, message):
    with pytest.raises(ConfigError) as error:
        validate_config(compose(["+head=unet", "+loss=dgs", override]))
    assert str(error.value).startswith(message) and "\n" not in str(error.value)


def test_no_source_views_for_a_generalizable_family_names_the_key_not_a_derived_one():
    with pytest.raises(ConfigError) as error:
        validate_config(compose(["+experiment=baselines/mvsnerf", "model.num_source_views=0"]))
    assert str(error.value) == ("model.num_source_views=0: model 'mvsnerf' renders from source views; expected an "
                                "integer >= 1 (0 only for a per-scene family)")
    assert validate_config(compose(["+experiment=baselines/semantic_nerf"])) is None  # per scene: 0 by default


@pytest.mark.parametrize("overrides", [[], ["+head=unet", "+loss=dgs"], ["+experiment=table4_id5"],
                                       ["+experiment=paper/gpnerf"], ["+experiment=baselines/gnt"]])
def test_defaults_and_presets_are_valid_and_still_checked(overrides):
    cfg = compose(overrides)
    assert validate_config(cfg) is None
    cfg.train.steps = 0  # the same composed config with one bad value is refused: the check ran on it
    with pytest.raises(ConfigError, match="train.steps=0: expected an integer >= 1"):
        validate_config(cfg)


def test_more_source_views_than_a_scene_offers_is_refused_naming_the_scene(tmp_path):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path}",
                   "model.num_source_views=4"])
    with pytest.raises(ConfigError, match=r"model.num_source_views=4 but scene 'layout_00' offers 3 source views"):
        check_data(cfg, build_components(cfg))


@pytest.mark.parametrize("override, message", [
    ("loss=rgb", "head 'unet' is trained by no term of loss 'rgb' (it renders no semantics)"),
    ("train.rays=2000", "train.rays=2000 exceeds the 1536 pixels of an image of scene 'layout_00' (32x48)"),
    ("eval.render_stride=3", "eval.render_stride=3 does not divide the image size of dataset.height x dataset.width"),
    ("dataset.width=13", "dataset.height x dataset.width = 32x13: image size 32x13 (HxW) is not a multiple of 4"),
])
def test_what_would_fail_or_mislead_later_is_refused_before_training(tmp_path, override, message):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'set'}", override])
    with pytest.raises(ConfigError) as error:
        check_data(cfg, build_components(cfg))
    assert message in str(error.value) and "\n" not in str(error.value)
    if override.startswith("dataset.width"):
        assert not (tmp_path / "set").exists()  # refused before the scenes were rendered


def _tiny(tmp_path, *extra):
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'set'}", *extra])
    components = build_components(cfg)
    check_data(cfg, components)  # generates the set; clean
    return cfg, components


def _fresh(cfg):
    return build_components(cfg)


def test_a_pose_that_is_not_rigid_is_refused_before_training_naming_the_line(tmp_path):
    cfg, _ = _tiny(tmp_path)
    trajectory = tmp_path / "set" / "layout_00" / "Sequence_1" / "traj_w_c.txt"
    lines = trajectory.read_text().splitlines()
    values = lines[2].split()
    values[1] = str(float(values[1]) + 0.5)  # shear the rotation
    lines[2] = " ".join(values)
    trajectory.write_text("\n".join(lines) + "\n")
    (tmp_path / "set" / "checksums.json").unlink()  # as a real dataset, which has no checksum list
    with pytest.raises(DataError, match=r"traj_w_c.txt:3: camera-to-world pose has rotation not orthonormal"):
        check_data(cfg, _fresh(cfg))


def test_a_truncated_image_is_found_by_full_validation_only(tmp_path, monkeypatch):
    cfg, _ = _tiny(tmp_path)
    label = tmp_path / "set" / "layout_00" / "Sequence_1" / "semantic_class" / "semantic_class_2.png"
    label.write_bytes(label.read_bytes()[: label.stat().st_size * 2 // 3])  # the header still reads
    (tmp_path / "set" / "checksums.json").unlink()  # as a real dataset, which has no checksum list
    monkeypatch.setattr(checks, "QUICK_FRAMES", 2)  # quick decodes frames 0 and 5 and the held-out 1 and 4, not 2
    check_data(cfg, _fresh(cfg))  # quick: file index, sizes from the headers, poses, a sample of frames
    full = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'set'}",
                    "dataset.validate=full"])
    with pytest.raises(DataError, match=r"semantic_class_2.png: unreadable image"):
        check_data(full, _fresh(full))


class LabelsOutOfRange(SceneDataset):
    """A dataset whose reader lets a label id past the class count through."""

    class_names = ("a", "b", "c")
    ignore_index = 255

    def scenes(self, split):
        return ("only",)

    def load_scene(self, name):
        frame = Frame(rgb=torch.zeros(4, 4, 3), depth=torch.ones(4, 4), semantic=torch.full((4, 4), 7),
                      intrinsics=torch.eye(3), c2w=torch.eye(4))
        return Scene(name, torch.eye(4)[None], torch.eye(3)[None], 4, 4, 0.1, 5.0, (0,), (), lambda i: frame)


def test_full_validation_checks_label_ids_against_the_class_count():
    [problem] = check_scene_files(LabelsOutOfRange(), ["only"], "full")
    assert check_scene_files(LabelsOutOfRange(), ["only"], "quick") == [problem]  # quick decodes a sample (here: all)
    assert problem == "scene 'only' frame 0: label 7 is neither a class id in [0, 3) nor the ignore index 255"


class HeldOutLabelOutOfRange(LabelsOutOfRange):
    """40 frames; only held-out frame 21 has a label past the class count (no spread of 8 picks it)."""

    def load_scene(self, name):
        def frame(index):
            semantic = torch.full((4, 4), 7 if index == 21 else 1)
            return Frame(rgb=torch.zeros(4, 4, 3), depth=torch.ones(4, 4), semantic=semantic, intrinsics=torch.eye(3),
                         c2w=torch.eye(4))

        held_out = (21,)
        return Scene(name, torch.eye(4).expand(40, 4, 4), torch.eye(3).expand(40, 3, 3), 4, 4, 0.1, 5.0,
                     tuple(i for i in range(40) if i not in held_out), held_out, frame)


def test_quick_validation_reads_every_held_out_frame_before_training():
    problems = check_scene_files(HeldOutLabelOutOfRange(), ["only"], "quick")  # (its cameras share a pose: noted too)
    assert "scene 'only' frame 21: label 7 is neither a class id in [0, 3) nor the ignore index 255" in problems


def test_a_damaged_file_in_a_dataset_root_says_how_to_regenerate(tmp_path):
    cfg, _ = _tiny(tmp_path)
    rgb = tmp_path / "set" / "layout_00" / "Sequence_1" / "rgb" / "rgb_2.png"
    rgb.write_bytes(rgb.read_bytes()[:100])
    with pytest.raises(DataError) as error:
        check_data(cfg, _fresh(cfg))
    message = str(error.value)
    assert "rgb_2.png: 100 bytes; expected" in message and f"regenerate: delete {tmp_path / 'set'}" in message


def test_a_damaged_cache_is_regenerated(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GPNERF_CACHE", str(tmp_path / "cache"))
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES])
    check_data(cfg, build_components(cfg))
    [cached] = (tmp_path / "cache" / "embedded_scenes").iterdir()
    rgb = cached / "layout_00" / "Sequence_1" / "rgb" / "rgb_2.png"
    original = rgb.read_bytes()
    rgb.write_bytes(original[:100])
    check_data(cfg, build_components(cfg))
    assert "cached embedded scenes" in capsys.readouterr().err and rgb.read_bytes() == original


def test_validation_off_skips_the_file_check(tmp_path):
    cfg, _ = _tiny(tmp_path)
    shutil.rmtree(tmp_path / "set" / "unseen_00" / "Sequence_1" / "depth")
    with pytest.raises(DataError, match="depth"):
        check_data(cfg, _fresh(cfg))
    off = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'set'}",
                   "dataset.validate=off", "eval.splits=[train]"])
    check_data(off, _fresh(off))


def test_a_generalizable_family_needs_a_source_view_a_per_scene_one_none(tmp_path):
    """``model.num_source_views=0`` is refused for a family that renders from source views (its config's default is
    not 0) when the config is checked, before anything is built; a per-scene family reads none."""
    from pipeline_check import TINY_MODEL, TINY_SCENES

    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES, f"dataset.root={tmp_path / 'scenes'}",
                   "model.num_source_views=0"])
    with pytest.raises(ConfigError, match=r"^model.num_source_views=0: model 'gnt' renders from source views; expected "
                                          r"an integer >= 1 \(0 only for a per-scene family\)$"):
        validate_config(cfg)

