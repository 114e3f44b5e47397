"""Which config sections define a trained model: the model's (with the parts its family built, mounted under it), the
loss's, and those of the add-ons its family built (a head, a depth source)."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gpnerf_core.config.compose import compose
from gpnerf_core.config.legacy import upgrade_sections
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.build import build_components
from gpnerf_core.model.checkpoint import check_resume_config, checkpoint_sections, model_sections
from pipeline_check import TINY_MODEL, TINY_SCENES


def test_a_model_is_defined_by_its_section_with_its_parts_and_the_add_ons_it_built():
    gnt = build_components(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES]))
    assert gnt.model_sections == ("model", "head", "loss")
    mvsnerf = build_components(compose(["+experiment=baselines/mvsnerf", *TINY_SCENES]))
    assert mvsnerf.model_sections == ("model", "loss")


def test_changing_a_part_of_the_model_is_refused_and_a_runtime_key_resumes():
    cfg = compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES])
    sections = build_components(cfg).model_sections
    old = OmegaConf.to_yaml(cfg, resolve=True)
    wider = OmegaConf.to_yaml(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES,
                                       "model.field_aggregator.width=8"]), resolve=True)
    with pytest.raises(ConfigError, match=r"model.field_aggregator.width: 16 -> 8"):
        check_resume_config(Path("c.pt"), old, wider, True, sections)
    checkpointed = OmegaConf.to_yaml(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *TINY_SCENES,
                                              "model.checkpoint_blocks=true"]), resolve=True)
    assert check_resume_config(Path("c.pt"), old, checkpointed, True, sections) == []


def test_a_checkpoints_recorded_sections_are_read_back():
    assert checkpoint_sections({"model_sections": ["model", "loss"]}) == ("model", "loss")
    assert checkpoint_sections({"model_sections": None}) == model_sections() == ("model", "head", "loss",
                                                                                 "depth_source")
    # written before the parts moved under the model: they are inside its section now
    assert upgrade_sections(["model", "feature_extractor", "field_aggregator", "ray_aggregator", "head", "loss"]) == (
        "model", "head", "loss")
