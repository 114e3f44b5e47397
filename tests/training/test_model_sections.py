"""Which config sections define a trained model: the model's, the loss's, and those of the parts its family built.
GNT's aggregators are not part of another family's model, so changing their options is no model change there."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.build import build_components
from gpnerf_core.model.checkpoint import check_resume_config, checkpoint_sections, model_sections
from pipeline_check import TINY_MODEL, TINY_SCENES


def test_gnt_is_defined_by_its_parts_and_mvsnerf_not_by_gnts():
    gnt = build_components(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES]))
    assert gnt.model_sections == ("model", "feature_extractor", "field_aggregator", "ray_aggregator", "head", "loss")
    mvsnerf = build_components(compose(["+experiment=baselines/mvsnerf", *TINY_SCENES]))
    assert mvsnerf.model_sections == ("model", "feature_extractor", "loss")


def test_changing_a_part_the_family_never_built_resumes_and_a_part_it_built_is_refused():
    cfg = compose(["+experiment=baselines/mvsnerf", *TINY_SCENES])
    sections = build_components(cfg).model_sections
    old = OmegaConf.to_yaml(cfg, resolve=True)
    wider = OmegaConf.to_yaml(compose(["+experiment=baselines/mvsnerf", *TINY_SCENES, "field_aggregator.width=8"]),
                              resolve=True)
    assert check_resume_config(Path("c.pt"), old, wider, True, sections) == []
    with pytest.raises(ConfigError, match="field_aggregator.width"):  # a checkpoint that recorded no sections
        check_resume_config(Path("c.pt"), old, wider, True, checkpoint_sections({}))
    planes = OmegaConf.to_yaml(compose(["+experiment=baselines/mvsnerf", *TINY_SCENES, "model.num_planes=16"]),
                               resolve=True)
    with pytest.raises(ConfigError, match="model.num_planes: 48 -> 16"):
        check_resume_config(Path("c.pt"), old, planes, True, sections)


def test_a_checkpoints_recorded_sections_are_read_back():
    assert checkpoint_sections({"model_sections": ["model", "loss"]}) == ("model", "loss")
    assert checkpoint_sections({"model_sections": None}) == model_sections()
