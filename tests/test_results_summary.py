"""examples/results/summarize.py's protocol section, on run folders written here in the layout ``run`` and
``finetune`` leave (``metrics.json``)."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "results" / "summarize.py"
MIOU = "miou/image_mean_present"


def write_run(runs: Path, name: str, unseen_miou: float, finetuned: list[float] | None = None) -> None:
    split = {MIOU: unseen_miou, "psnr/clamped": 20.0, "ssim/gaussian11": 0.7, "acc/total": 0.9, "acc/class_mean": 0.8}
    metrics = {"eval": {"train_heldout": dict(split), "unseen": split}, "train": {"seconds": 100.0, "steps": 1200},
               "parameters": {"total": 1_000_000}}
    if finetuned is not None:
        metrics["finetune"] = {"curve": [{"step": 100 * k, MIOU: v, "psnr/clamped": 21.0}
                                         for k, v in enumerate(finetuned)]}
    (runs / name).mkdir(parents=True)
    (runs / name / "metrics.json").write_text(json.dumps(metrics))


def summary(work: Path) -> str:
    result = subprocess.run([sys.executable, str(SCRIPT), str(work)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_each_protocol_count_gets_table_1_with_its_orderings_and_its_fine_tuning(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        for prefix, miou in (("layouts_n8", 0.70), ("layouts_n8_semantic_ray", 0.50), ("layouts_n8_neuray", 0.55)):
            write_run(runs, f"{prefix}_s{seed}", miou + 0.01 * seed)
    write_run(runs, "finetune_layouts_n8_s0", 0.70, finetuned=[0.70, 0.75, 0.80, 0.79])
    text = summary(tmp_path)
    heading = ("## The generalized protocol (8 training layouts, 1200 steps, 4 unseen layouts, last step's weights): "
               "Table 1's generalization rows")
    section = text[text.index(heading):]
    assert "| GP-NeRF > Semantic-Ray | +20.0, +20.0, +20.0 | yes |" in section
    assert "| Semantic-Ray > NeuRay + semantic head | -5.0, -5.0, -5.0 | yes |" in section  # a reversal holds too
    assert "| MVSNeRF + semantic head (`baselines/mvsnerf`) |" in section and "seed 0, seed 1, seed 2 |" in section
    fine = section[section.index("fine-tuned on unseen_00"):]
    assert "| steps (s) to mIoU 0.70 | steps (s) to mIoU 0.80 |" in fine
    assert "| GP-NeRF (ID 5) | 0 | 0: 0.700, 100: 0.750, 200: 0.800, 300: 0.790 | 21.00 | 100 | 0 (0) | 200 (67) |" in fine
    assert "| Semantic-Ray | 0 | not run | | | | |" in fine


def test_a_weight_averaged_protocol_gets_its_own_tables_beside_the_last_step_one(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        for prefix, miou in (("layouts_n8", 0.70), ("layouts_n8_semantic_ray", 0.50),
                             ("layouts_n8_ema", 0.80), ("layouts_n8_ema_semantic_ray", 0.82)):
            write_run(runs, f"{prefix}_s{seed}", miou + 0.01 * seed)
    text = summary(tmp_path)
    last = text.index("(8 training layouts, 1200 steps, 4 unseen layouts, last step's weights): Table 1's")
    averaged = text.index("(8 training layouts, 1200 steps, 4 unseen layouts, weight average (train.ema_decay)): Table 1's")
    assert last < averaged
    assert "| GP-NeRF > Semantic-Ray | +20.0, +20.0, +20.0 | yes |" in text[last:averaged]
    assert "| GP-NeRF > Semantic-Ray | -2.0, -2.0, -2.0 | yes |" in text[averaged:]


def test_without_protocol_runs_there_is_no_protocol_section(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "layouts_n8_s0", 0.7)  # the layouts curve alone
    assert "generalized protocol (" not in summary(tmp_path)


def test_the_layout_curve_is_per_seed_with_each_step_up_in_width_paired_by_seed(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        for count, miou in ((4, 0.60), (8, 0.62), (16, 0.70)):
            write_run(runs, f"layouts_n{count}_s{seed}", miou + 0.01 * seed)
    write_run(runs, "layouts_n32_s0", 0.65)
    section = summary(tmp_path).split("## Training layouts")[1].split("\n## ")[0]
    assert "| 16 | 2400 | 0.710 +- 0.010 | 0.700, 0.710, 0.720 | 0.710 +- 0.010 | 20.00 +- 0.00 |" in section
    assert section.count("seed 1, seed 2 |") == 1  # the 32-layout row names its missing seeds
    assert "| 8 -> 16 layouts | +8.0, +8.0, +8.0; **+8.0** | yes | +0.0, +0.0, +0.0; **+0.0** | no (signs differ) |" in section
    assert "| 16 -> 32 layouts | -5.0; **-5.0** | n/a |" in section  # one paired seed: no verdict
    steps = [line.split(" |")[0] for line in section.splitlines() if " -> " in line]
    assert steps == ["| 4 -> 8 layouts", "| 8 -> 16 layouts", "| 16 -> 32 layouts", "| 4 -> 16 layouts",
                     "| 8 -> 32 layouts", "| 4 -> 32 layouts"]  # each step up, then the wider ones


def test_a_records_folder_is_summarized_with_each_batchs_provenance(tmp_path):
    records = tmp_path / "records"
    write_run(records / "runs", "layouts_n8_ema_s1", 0.80)
    write_run(records / "runs", "layouts_n8_ema_semantic_ray_s1", 0.78)
    write_run(records / "runs", "finetune_layouts_n8_ema_semantic_ray_s1", 0.78, finetuned=[0.78, 0.79, 0.79, 0.79])
    (records / "provenance").mkdir()
    for day in ("2026-12-04T181853Z", "2026-12-05T090000Z"):
        (records / "provenance" / f"{day}.txt").write_text(f"commit abc\nstarted {day} stages: protocol\n")
    text = summary(records)
    assert text.index("started 2026-12-04T181853Z") < text.index("started 2026-12-05T090000Z") < text.index("## ")
    assert "| Semantic-Ray | 1 | 0: 0.780, 100: 0.790, 200: 0.790, 300: 0.790 | 21.00 | 100 | 0 (0) | not reached |" in text
