import json

import pytest
import yaml

from gpnerf_core.errors import DataError
from gpnerf_core.tools.reporting.runs import find_runs, format_table


def write_run(folder, loss, joint, miou, seed=0, head="unet", model="gnt"):
    folder.mkdir(parents=True)
    config = {"head": {"name": head} if head else None, "loss": loss,
              "model": {"name": model, "semantic_field": {"joint_attention": joint}}, "seed": seed,
              "out_dir": str(folder)}
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    metrics = {"train": {"steps": 10, "seconds": 1.5},
               "eval": {"train_heldout": {"miou/image_mean_present": miou, "psnr/clamped": 20.0},
                        "unseen": {"miou/image_mean_present": miou / 2}}}
    (folder / "metrics.json").write_text(json.dumps(metrics))


def test_rows_are_matched_to_table4_ids(tmp_path):
    write_run(tmp_path / "0", {"name": "ce", "sd_weight": 0, "dgs_weight": 0, "teacher_stop_grad": True}, False, 0.5)
    write_run(tmp_path / "1", {"name": "sd", "sd_weight": 0.25, "dgs_weight": 0, "teacher_stop_grad": False}, True, 0.4)
    write_run(tmp_path / "2", {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}, True, 0.6)
    table = format_table(find_runs([tmp_path])).splitlines()
    assert len(table) == 5
    assert table[2].split("|")[17].strip() == "1" and "56.45" in table[2]
    assert table[3].split("|")[17].strip() == "3" and "| 40.00 | 20.00 | 20.00 |" in table[3]
    assert table[4].split("|")[17].strip() == "5" and "59.92" in table[4]
    assert table[4].endswith("| 48.53 / 59.92 |") and table[2].endswith("| - |")  # GP-NeRF's Table 1 row: ID 5 only


def test_the_compared_families_sit_beside_the_papers_table1_row(tmp_path):
    ce = {"name": "ce", "sd_weight": 0, "dgs_weight": 0}
    write_run(tmp_path / "sr", ce, True, 0.5, head=None, model="semantic_ray")
    write_run(tmp_path / "mvs", ce, True, 0.4, head=None, model="mvsnerf")
    write_run(tmp_path / "colour", {"name": "rgb"}, True, 0.4, head=None, model="neuray")  # not the semantic method
    write_run(tmp_path / "snerf", ce, True, 0.6, head=None, model="semantic_nerf")  # per scene: Table 1's own row
    write_run(tmp_path / "grid", ce, True, 0.7, head=None, model="semantic_nerf")
    config = yaml.safe_load((tmp_path / "grid" / "config.yaml").read_text())
    config["model"]["field"] = "grid"  # its grid option is not the paper's method
    (tmp_path / "grid" / "config.yaml").write_text(yaml.safe_dump(config))
    rows = {row.split("|")[1].strip(): row for row in format_table(find_runs([tmp_path])).splitlines()[2:]}
    assert rows["sr"].split("|")[3].strip() == "semantic_ray" and rows["sr"].endswith("| 41.59 / 57.15 |")
    assert rows["mvs"].endswith("| 23.41 / 39.82 |") and rows["colour"].endswith("| - |")
    assert rows["snerf"].endswith("| 75.06 / 91.24 |") and rows["grid"].endswith("| - |")


def test_fine_tuned_runs_sit_beside_table1s_fine_tuning_rows(tmp_path):
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    ce = {"name": "ce", "sd_weight": 0, "dgs_weight": 0}
    write_run(tmp_path / "gpnerf_ft", dgs, True, 0.8)
    write_run(tmp_path / "sr_ft", ce, True, 0.7, head=None, model="semantic_ray")
    for name in ("gpnerf_ft", "sr_ft"):  # what finetune writes beside the evaluation: its curve
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        metrics["finetune"] = {"curve": [{"step": 0}, {"step": 10}]}
        (tmp_path / name / "metrics.json").write_text(json.dumps(metrics))
    write_run(tmp_path / "gpnerf", dgs, True, 0.6)  # generalization: its own row
    rows = {row.split("|")[1].strip(): row for row in format_table(find_runs([tmp_path])).splitlines()[2:]}
    assert rows["gpnerf_ft"].endswith("| 87.72 / 93.84 |") and rows["sr_ft"].endswith("| 75.96 / 91.06 |")
    assert rows["gpnerf"].endswith("| 48.53 / 59.92 |")


def test_missing_path_is_an_error(tmp_path):
    with pytest.raises(DataError, match="found nothing"):
        find_runs([tmp_path / "nope"])


def test_runs_differing_only_by_seed_form_one_row_with_mean_and_std(tmp_path):
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    for seed, miou in ((0, 0.5), (1, 0.6), (2, 0.7)):
        write_run(tmp_path / f"s{seed}", dgs, True, miou, seed=seed)
    write_run(tmp_path / "other", {**dgs, "dgs_weight": 0.5}, True, 0.3)  # another method: its own row
    table = format_table(find_runs([tmp_path])).splitlines()
    assert len(table) == 4
    row = table[3]
    assert row.startswith("| s0 (+2) | 0,1,2 | gnt |")
    assert "| 60.00 +- 10.00 (n=3) | 30.00 +- 5.00 (n=3) | 20.00 +- 0.00 (n=3) |" in row


def test_an_eval_of_a_runs_checkpoint_is_its_own_row_not_another_seed(tmp_path):
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    write_run(tmp_path / "run", dgs, True, 0.5)
    write_run(tmp_path / "eval", dgs, True, 0.5)
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    metrics["checkpoint"] = str(tmp_path / "run" / "checkpoints" / "step_0000010.pt")
    (tmp_path / "eval" / "metrics.json").write_text(json.dumps(metrics))
    table = format_table(find_runs([tmp_path])).splitlines()
    assert len(table) == 4 and all("(n=2)" not in row for row in table)


def test_a_third_party_loss_or_head_never_gets_the_papers_number(tmp_path):
    look_alike = {"name": "my_loss", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    write_run(tmp_path / "a", look_alike, True, 0.5)
    write_run(tmp_path / "b", {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True},
              True, 0.5, head="my_head")
    for row in format_table(find_runs([tmp_path])).splitlines()[2:]:
        assert row.endswith("| - | - | - | - |") and "59.92" not in row


def test_runs_written_by_other_versions_group_when_only_empty_defaults_and_other_commands_differ(tmp_path):
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    write_run(tmp_path / "old", dgs, True, 0.5, seed=0)
    write_run(tmp_path / "new", dgs, True, 0.7, seed=1)
    config = yaml.safe_load((tmp_path / "new" / "config.yaml").read_text())
    config.update(dataset={"scenes": [], "unseen_scenes": []}, render={"frames": 30}, finetune={"points": 4})
    (tmp_path / "new" / "config.yaml").write_text(yaml.safe_dump(config))
    rows = format_table(find_runs([tmp_path])).splitlines()[2:]
    assert len(rows) == 1 and "60.00 +- 14.14 (n=2)" in rows[0]


def test_a_schema_key_a_run_predates_counts_as_its_default(tmp_path):
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    for name, seed, train in (("old", 0, {"steps": 600}), ("new", 1, {"steps": 600, "warmup_steps": 0}),
                              ("warm", 2, {"steps": 600, "warmup_steps": 30})):
        write_run(tmp_path / name, dgs, True, 0.5 + 0.1 * seed, seed=seed)
        config = yaml.safe_load((tmp_path / name / "config.yaml").read_text())
        config["train"] = train
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(config))
    rows = format_table(find_runs([tmp_path])).splitlines()[2:]
    assert len(rows) == 2
    assert any(row.startswith("| new (+1) | 1,0 |") or row.startswith("| new (+1) | 0,1 |") for row in rows), rows


def test_the_pareto_front_keeps_the_methods_nothing_beats_on_both_axes():
    from gpnerf_core.tools.reporting.speed_accuracy import ACCURACY, COSTS, Method, Point, pareto_front

    miou, seconds, throughput = ACCURACY[0], COSTS[0], COSTS[1]

    def method(label, acc, cost):
        return Method(label, [0], {miou.name: Point(acc, 0, 1), seconds.name: Point(cost, 0, 1),
                                   throughput.name: Point(1000 / cost, 0, 1)}, {})

    methods = [method("fast", 0.5, 100), method("slow_good", 0.7, 400), method("dominated", 0.45, 200),
               method("tie", 0.5, 100), method("middle", 0.6, 250)]
    front = [m.label for m in pareto_front(methods, miou, seconds)]
    assert front == ["fast", "tie", "middle", "slow_good"]  # equal on both axes: neither beats the other
    assert [m.label for m in pareto_front(methods, miou, throughput)] == ["slow_good", "middle", "fast", "tie"]


def test_report_chart_writes_png_csv_and_the_fronts(tmp_path):
    import subprocess
    import sys

    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    ce = {"name": "ce", "sd_weight": 0, "dgs_weight": 0, "teacher_stop_grad": True}
    for name, loss, seed, miou, seconds in (("full_s0", dgs, 0, 0.6, 300), ("full_s1", dgs, 1, 0.7, 320),
                                            ("ce", ce, 0, 0.5, 200)):
        write_run(tmp_path / "runs" / name, loss, True, miou, seed=seed)
        metrics_file = tmp_path / "runs" / name / "metrics.json"
        metrics = json.loads(metrics_file.read_text())
        metrics["train"].update(seconds=seconds, rays_per_second=1000.0)
        metrics["parameters"] = {"total": 2_000_000}
        metrics_file.write_text(json.dumps(metrics))
    done = subprocess.run([sys.executable, "-m", "gpnerf_core", "report", str(tmp_path / "runs"), "--chart",
                           str(tmp_path / "chart")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    front = "mIoU held-out vs training time: GP-NeRF (unet + ce, Table 4 ID 2), GP-NeRF (unet + dgs, Table 4 ID 5)"
    assert front in done.stdout
    assert (tmp_path / "chart" / "speed_accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "chart" / "headline.png").exists()  # no run measured the seconds per frame
    rows = (tmp_path / "chart" / "speed_accuracy.csv").read_text().splitlines()
    assert rows[0].startswith("method,seeds,n,mIoU held-out (per-image mIoU) mean,mIoU held-out std")
    full = next(row for row in rows if row.startswith('"GP-NeRF (unet + dgs, Table 4 ID 5)",'))
    assert full.startswith('"GP-NeRF (unet + dgs, Table 4 ID 5)",0 1,2,0.65,0.0707107')
    assert rows[0].endswith("parameters (millions) mean,parameters std") and full.endswith(",1000,0,2,0")
    assert front in (tmp_path / "chart" / "pareto.txt").read_text()


def test_report_chart_refuses_a_file_and_runs_with_nothing_to_draw(tmp_path):
    import subprocess
    import sys

    (tmp_path / "runs" / "failed").mkdir(parents=True)
    (tmp_path / "runs" / "failed" / "config.yaml").write_text("seed: 0\n")
    (tmp_path / "runs" / "failed" / "error.json").write_text('{"error": "boom"}')
    (tmp_path / "a_file").write_text("")
    for chart, message in (("a_file", "--chart {}: expected a folder, found a file"),
                           ("chart", "--chart: no run has both an accuracy")):
        done = subprocess.run([sys.executable, "-m", "gpnerf_core", "report", str(tmp_path / "runs"), "--chart",
                               str(tmp_path / chart)], capture_output=True, text=True, timeout=300)
        assert done.returncode == 2 and message.format(tmp_path / chart) in done.stderr, done.stderr
    assert not (tmp_path / "chart").exists()


def test_chart_labels_name_the_method_and_tell_apart_two_variants_of_one():
    from gpnerf_core.tools.reporting.runs import find_runs, group_runs, method_labels

    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
        write_run(root / "main", dgs, True, 0.6)
        write_run(root / "cosine", dgs, True, 0.5)
        config = yaml.safe_load((root / "cosine" / "config.yaml").read_text())
        config["train"] = {"lr_schedule": "cosine"}
        (root / "cosine" / "config.yaml").write_text(yaml.safe_dump(config))
        write_run(root / "mine", {"name": "focal"}, True, 0.4, head="mine")
        groups = group_runs(find_runs([root]))
        labels = sorted(method_labels(groups))
    assert labels == ["GP-NeRF (mine + focal)", "GP-NeRF (unet + dgs, Table 4 ID 5) [lr_schedule=cosine]",
                      "GP-NeRF (unet + dgs, Table 4 ID 5) [lr_schedule=exponential]"]


def test_chart_labels_name_the_size_first_and_stay_unique(tmp_path):
    """Two sizes of one method: the legend names the model keys that differ (not the folders); a third variant that
    shares the first keys shown gets the key that tells it apart."""
    from gpnerf_core.tools.reporting.runs import find_runs, group_runs, method_labels

    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    variants = {
        "default": {"field_aggregator": {"num_blocks": 4}, "dataset": {"near": 0.2}},
        "sized": {"model": {"fine_samples": 0, "num_source_views": 3}, "field_aggregator": {"num_blocks": 2},
                  "dataset": {"near": 0.59}, "train": {"rays": 64}},
        "sized_lr": {"model": {"fine_samples": 0, "num_source_views": 3}, "field_aggregator": {"num_blocks": 2},
                     "dataset": {"near": 0.59}, "train": {"rays": 64, "lr_schedule": "cosine"}},
    }
    for name, changes in variants.items():
        write_run(tmp_path / name, dgs, True, 0.6)
        config = yaml.safe_load((tmp_path / name / "config.yaml").read_text())
        for section, values in changes.items():
            config.setdefault(section, {}).update(values)
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(config))
    groups = group_runs(find_runs([tmp_path]))
    labels = dict(zip((g.runs[0].folder.name for g in groups), method_labels(groups)))
    assert labels["sized"] == ("GP-NeRF (unet + dgs, Table 4 ID 5) [num_blocks=2, fine_samples=0, num_source_views=3, "
                               "near=0.59, lr_schedule=exponential, +1 more]")  # the model's keys (its parts') first
    assert labels["sized_lr"].endswith("near=0.59, lr_schedule=cosine, +1 more]")
    assert labels["default"] == ("GP-NeRF (unet + dgs, Table 4 ID 5) [num_blocks=4, fine_samples=16, num_source_views=10, "
                                 "near=0.2, +2 more]")
    assert len(set(labels.values())) == 3 and not any(name in label for name, label in labels.items())


def test_a_third_party_head_shows_its_table4_switches_but_no_paper_number(tmp_path):
    from gpnerf_core.tools.reporting.runs import RunRow

    config = {"head": {"name": "fancy_head"}, "model": {"semantic_field": {"joint_attention": True}},
              "loss": {"name": "dgs", "sd_weight": 1.0, "dgs_weight": 0.5, "teacher_stop_grad": True}, "seed": 0}
    metrics = {"eval": {"unseen": {"miou/image_mean_present": 0.5}}, "train": {"steps": 2, "seconds": 1.0}}
    row = RunRow(tmp_path / "fancy", config, metrics)
    assert row.switches() == (True, True, True, True) and row.paper_switches() is None
    line = format_table([row]).splitlines()[2]
    assert "| fancy_head | dgs | yes | yes | yes | yes |" in line
    assert line.rstrip().endswith("| - | - | - |")  # no Table 4 ID or paper numbers beside a third-party head


def test_another_family_with_gp_nerf_decoding_is_not_a_table4_row(tmp_path):
    """``baselines/semantic_ray_unet``: the U-Net head and GP-NeRF's loss set on Semantic-Ray's field. Joint
    attention is GNT's switch (shown as -) and no Table 4 ID or GP-NeRF number sits beside it."""
    from gpnerf_core.tools.reporting.runs import RunRow

    config = {"head": {"name": "unet"}, "model": {"name": "semantic_ray"},
              "loss": {"name": "dgs", "sd_weight": 1.0, "dgs_weight": 0.5, "teacher_stop_grad": True}, "seed": 0}
    metrics = {"eval": {"unseen": {"miou/image_mean_present": 0.5}}, "train": {"steps": 2, "seconds": 1.0}}
    row = RunRow(tmp_path / "semantic_ray_unet", config, metrics)
    assert row.switches() == (None, True, True, True) and row.paper_switches() is None
    assert row.paper_table1() is None
    line = format_table([row]).splitlines()[2]
    assert "| semantic_ray | unet | dgs | - | yes | yes | yes |" in line
    assert line.rstrip().endswith("| - | - | - | - |")


@pytest.mark.parametrize("metrics, problem", [
    ([1, 2], "it holds a list, not an object"),
    ({"eval": "x"}, "'eval' is a str"),
    ({"eval": {"unseen": {"miou/image_mean_present": "high"}}}, "'eval.unseen.miou/image_mean_present' is text"),
    ({"train": {"steps": "many"}}, "'train.steps' is a str, not a number"),
])
def test_a_metrics_file_of_another_shape_is_one_line_naming_it(tmp_path, metrics, problem):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text("seed: 0\n")
    (tmp_path / "run" / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(DataError, match=r"metrics.json: not a gpnerf-core run's metrics \(" + problem.replace("(", r"\(")):
        find_runs([tmp_path])


def test_the_headline_panel_leads_the_chart_and_is_drawn_alone_too(tmp_path):
    from PIL import Image

    from gpnerf_core.tools.reporting.speed_accuracy import Method, Point, draw

    def method(label, miou, seconds_per_frame):
        return Method(label, [0, 1], {"mIoU held-out": Point(miou, 0.01, 2), "rendering": Point(seconds_per_frame, 0.1, 2),
                                      "parameters": Point(2.5, 0, 2)}, {})

    fronts = draw([method("GP-NeRF", 0.77, 2.4), method("GP-NeRF sized", 0.76, 0.8), method("worse", 0.6, 3.0)],
                  tmp_path)
    assert fronts["mIoU held-out vs rendering"] == ["GP-NeRF sized", "GP-NeRF"]
    alone = Image.open(tmp_path / "headline.png")
    chart = Image.open(tmp_path / "speed_accuracy.png")
    assert alone.size[0] >= 700 and chart.size[1] > alone.size[1]  # the grid (1 x 2 panels) below the headline


def test_chart_labels_name_where_a_run_sampled(tmp_path):
    from gpnerf_core.tools.reporting.runs import find_runs, group_runs, method_labels

    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    for name, sampler, source in (("uniform", None, None), ("first_pass", "depth", None),
                                  ("swept", "depth", {"name": "cost_volume", "planes": 64})):
        write_run(tmp_path / name, dgs, True, 0.6)
        config = yaml.safe_load((tmp_path / name / "config.yaml").read_text())
        if sampler:
            config["model"]["sampler"] = sampler
        if source:
            config["depth_source"] = source
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(config))
    groups = group_runs(find_runs([tmp_path]))
    labels = dict(zip((g.runs[0].folder.name for g in groups), method_labels(groups)))
    assert labels == {"uniform": "GP-NeRF (unet + dgs, Table 4 ID 5)",
                      "first_pass": "GP-NeRF (unet + dgs, Table 4 ID 5) (depth samples: first pass)",
                      "swept": "GP-NeRF (unet + dgs, Table 4 ID 5) (depth samples: cost_volume)"}


def test_report_of_built_in_runs_imports_no_third_party_plugin(tmp_path):
    import os
    import subprocess
    import sys

    plugins = tmp_path / "plugins"
    info = plugins / "marker_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: marker-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[gpnerf]\nmarker_plugin = marker_plugin\n")
    marker = tmp_path / "imported"
    (plugins / "marker_plugin.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    dgs = {"name": "dgs", "sd_weight": 0.25, "dgs_weight": 0.25, "teacher_stop_grad": True}
    write_run(tmp_path / "runs" / "s0", dgs, True, 0.5)
    env = {k: v for k, v in os.environ.items() if k != "GPNERF_DISABLE_PLUGIN_AUTOLOAD"}
    env.update(PYTHONPATH=os.pathsep.join([str(plugins), env.get("PYTHONPATH", "")]), GPNERF_CACHE=str(tmp_path / "c"))
    result = subprocess.run([sys.executable, "-m", "gpnerf_core", "report", str(tmp_path / "runs")], env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "| s0 |" in result.stdout and not marker.exists()


def test_chart_labels_name_each_method_then_its_variant(tmp_path):
    from gpnerf_core.tools.reporting.runs import find_runs, group_runs, method_labels

    write_run(tmp_path / "mvsnerf", {"name": "ce"}, True, 0.4, head=None, model="mvsnerf")
    write_run(tmp_path / "mvsnerf_unet", {"name": "dgs"}, True, 0.4, head="unet", model="mvsnerf")
    write_run(tmp_path / "splat", {"name": "image"}, True, 0.4, head=None, model="mvsplat")
    write_run(tmp_path / "ray", {"name": "ce"}, True, 0.4, head=None, model="semantic_ray")
    write_run(tmp_path / "mine", {"name": "ce"}, True, 0.4, head=None, model="mine")
    write_run(tmp_path / "gnt", {"name": "rgb"}, True, 0.4, head=None)
    config = yaml.safe_load((tmp_path / "gnt" / "config.yaml").read_text())
    config["model"]["semantic_field"]["enabled"] = False
    (tmp_path / "gnt" / "config.yaml").write_text(yaml.safe_dump(config))
    groups = group_runs(find_runs([tmp_path]))
    labels = dict(zip((g.runs[0].folder.name for g in groups), method_labels(groups)))
    assert labels == {"mvsnerf": "MVSNeRF + semantic head (ce)", "mvsnerf_unet": "MVSNeRF + unet head (dgs)",
                      "splat": "MVSplat (image)", "ray": "Semantic-Ray (ce)", "mine": "mine (ce)",
                      "gnt": "GNT (no head + rgb)"}
