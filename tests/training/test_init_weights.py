"""model.init: an official GNT checkpoint's layout maps onto the extractor and the field/ray aggregators."""

import pytest
import torch

from gpnerf_core.model.build import build_model
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import DataError
from gpnerf_core.model.weights import init_weights
from pipeline_check import TINY_MODEL


def tiny_model(seed, *extra):
    torch.manual_seed(seed)
    return build_model(compose(["+head=unet", "+loss=dgs", *TINY_MODEL, *extra]), num_classes=9)


def gnt_checkpoint(model):
    """The dict GNT's ``save_model`` writes, with GNT's own module names (written from GNT's model code):
    ``net_coarse`` = GNT(rgbfeat_fc, view_crosstrans, view_selftrans, q_fcs, norm, rgb_fc), ``feature_net`` =
    ResUNet, plus optimizer and scheduler states."""
    net_coarse = {}
    for key, value in model.field.state_dict().items():
        net_coarse[key.replace("blocks.", "view_crosstrans.", 1) if key.startswith("blocks.") else key] = value
    for key, value in model.ray.state_dict().items():
        net_coarse[key.replace("blocks.", "view_selftrans.", 1) if key.startswith("blocks.") else key] = value
    feature_net = {k.removeprefix("backbone."): v for k, v in model.extractor.state_dict().items() if k.startswith("backbone.")}
    return {
        "net_coarse": net_coarse,
        "feature_net": feature_net,
        "optimizer": {"state": {}, "param_groups": [{"lr": 5e-4}]},
        "scheduler": {"last_epoch": 250000},
    }


def test_gnt_checkpoint_loads_into_extractor_and_aggregators(tmp_path):
    source = tiny_model(0)
    path = tmp_path / "model_250000.pth"
    torch.save(gnt_checkpoint(source), path)
    target = tiny_model(1)
    report = init_weights(target, path)
    for prefix in ("field.", "ray.", "extractor.backbone."):
        keys = [k for k in source.state_dict() if k.startswith(prefix)]
        assert keys and all(k in report.loaded for k in keys)
        for key in keys:
            assert torch.equal(target.state_dict()[key], source.state_dict()[key]), key
    # What GNT has no weights for keeps its initialisation and is reported.
    assert any(k.startswith("extractor.fpn.") for k in report.missing)
    assert any(k.startswith("head.") for k in report.missing) and any(k.startswith("semantic.") for k in report.missing)
    assert not any(k.startswith("extractor.backbone.") for k in report.missing)
    assert report.ignored == ["optimizer", "scheduler"] and report.unexpected == []
    assert "(gnt): loaded" in str(report) and "head.decoder.*" in str(report)


def test_gnt_checkpoint_with_an_unknown_key_is_one_line_naming_file_and_key(tmp_path):
    checkpoint = gnt_checkpoint(tiny_model(0))
    checkpoint["net_coarse"]["view_crosstrans.0.extra.weight"] = torch.zeros(3)
    path = tmp_path / "gnt.pth"
    torch.save(checkpoint, path)
    with pytest.raises(DataError) as error:
        init_weights(tiny_model(1), path)
    message = str(error.value)
    assert "\n" not in message and str(path) in message and "net_coarse.view_crosstrans.0.extra.weight" in message
    report = init_weights(tiny_model(1), path, strict=False)
    assert report.unexpected == ["net_coarse.view_crosstrans.0.extra.weight"] and report.loaded


def test_gnt_checkpoint_of_another_width_names_the_tensor(tmp_path):
    path = tmp_path / "wide.pth"
    torch.save(gnt_checkpoint(tiny_model(0, "model.field_aggregator.width=32", "model.feature_extractor.fpn_channels=8")), path)
    with pytest.raises(DataError, match=r"'net_coarse\.rgbfeat_fc\.0\.weight' has shape \[32, 35\] but 'field\.rgbfeat_fc\.0\.weight'"):
        init_weights(tiny_model(1), path)


def test_file_of_no_known_format_is_refused(tmp_path):
    path = tmp_path / "other.pth"
    torch.save({"state_dict": {}}, path)
    with pytest.raises(DataError, match="neither a gpnerf-core checkpoint nor a format model GeneralizableNeRF reads"):
        init_weights(tiny_model(1), path)
