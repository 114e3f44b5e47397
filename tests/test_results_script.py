"""examples/results/regenerate.sh's queue, run with a stand-in for Python that records each job instead of training."""

import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "results" / "regenerate.sh"

# Stands in for `python`: `-c` (the provenance line) prints a line; `-m gpnerf_core <command> ... out_dir=<run>`
# logs "start/end <run name>" to $JOURNAL, prints its arguments (the job's log) and fails for the run named in $FAIL.
STAND_IN = r"""#!/usr/bin/env bash
[[ $1 == -c ]] && { echo "stand-in 0.0"; exit 0; }
name=unknown
for argument in "$@"; do
  case $argument in out_dir=*) name=${argument##*/} ;; --out) next=out ;; *) [[ ${next:-} == out ]] && name=stress_${argument##*/}; next= ;; esac
done
echo "start $name" >> "$JOURNAL"; sleep 0.2; echo "end $name" >> "$JOURNAL"; echo "$*"
[[ $name == "${FAIL:-}" ]] && exit 3
exit 0
"""


def regenerate(tmp_path, stages, fail="", **extra_env):
    tmp_path.mkdir(exist_ok=True)
    python = tmp_path / "python"
    python.write_text(STAND_IN)
    python.chmod(0o755)
    journal = tmp_path / "journal.txt"
    env = {"PATH": "/usr/bin:/bin", "PYTHON": str(python), "JOURNAL": str(journal), "FAIL": fail, "POLL_SECONDS": "0.1", **extra_env}
    result = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "work"), stages], env=env, capture_output=True,
                            text=True, timeout=120)
    lines = journal.read_text().splitlines() if journal.exists() else []
    return result, lines


def test_one_queue_runs_every_stage_and_a_job_starts_after_the_runs_it_needs(tmp_path):
    result, journal = regenerate(tmp_path, "finetune stress table4")
    assert result.returncode == 0, result.stderr
    done = sorted(p.name for p in (tmp_path / "work" / "done").iterdir())
    assert len(done) == 15 + 2 + 3 and "stress_id5" in done and "finetune_id5_s2" in done
    for dependent, needs in (("finetune_id5_s1", ["id5_s1"]), ("stress_id5", ["id5_s0", "id5_s1", "id5_s2"])):
        assert all(journal.index(f"end {need}") < journal.index(f"start {dependent}") for need in needs)
    # Jobs that need nothing go first: every Table 4 run starts before any stress or fine-tuning job ends (the last
    # Table 4 run and the first dependent job are launched together, so their journal lines come in either order).
    first_dependent = min(journal.index(f"end {name}") for name in ("stress_id1", "stress_id5", "finetune_id5_s0"))
    assert max(journal.index(f"start id{i}_s{s}") for i in range(1, 6) for s in range(3)) < first_dependent

    again, journal_again = regenerate(tmp_path, "finetune stress table4")
    assert again.returncode == 0 and journal_again == journal  # everything done: nothing runs again
    assert again.stdout.count("skip ") == 20


def test_a_failed_run_fails_what_needs_it_and_stops_before_the_report(tmp_path):
    result, journal = regenerate(tmp_path, "table4 finetune report", fail="id5_s1")
    assert result.returncode == 1
    assert "FAILED id5_s1" in result.stderr and "FAILED finetune_id5_s1: it needs id5_s1" in result.stderr
    assert "start finetune_id5_s1" not in journal and "end finetune_id5_s2" in journal  # the others went on
    assert "no report" in result.stderr and not (tmp_path / "work" / "report_table4.md").exists()
    needing_what_was_not_asked_for, _ = regenerate(tmp_path / "other", "stress")
    assert needing_what_was_not_asked_for.returncode == 1
    assert "stress_id1: it needs id1_s0, which failed or is neither done nor in the stages asked for" in (
        needing_what_was_not_asked_for.stderr)


def test_an_unknown_stage_is_one_line_listing_the_known(tmp_path):
    result, journal = regenerate(tmp_path, "table4 tabel5")
    assert result.returncode == 2 and journal == []
    assert result.stderr == "unknown stage 'tabel5' (known: table4 methods baselines grid gaussians samplers per_scene per_scene_gaussians gaussian_grouping mask_rcnn layouts protocol stress instance finetune report records)\n"


def test_the_protocol_shares_its_gp_nerf_runs_with_the_layouts_curve(tmp_path):
    result, journal = regenerate(tmp_path, "layouts protocol", PROTOCOL_LAYOUTS="8")
    assert result.returncode == 0, result.stderr
    assert all(journal.count(f"start layouts_n8_s{s}") == 1 for s in range(3))  # one job each, asked for by both stages
    # The longest runs first: the first two jobs (started side by side, so their journal lines come in either order).
    assert set([line for line in journal if line.startswith("start ")][:2]) == {
        "start layouts_n32_s0", "start layouts_n32_s1"}
    done = {p.name for p in (tmp_path / "work" / "done").iterdir()}
    families = ("", "_semantic_ray", "_neuray", "_mvsnerf")
    assert {f"layouts_n8{f}_s{s}" for f in families for s in range(3)} <= done
    for family in families:
        for seed in range(3):
            run = f"layouts_n8{family}_s{seed}"
            assert journal.index(f"end {run}") < journal.index(f"start finetune_{run}")
    assert len(done) == 3 * 3 + 12 + 12  # the other three counts x 3 seeds, the protocol's runs, their fine-tuning


def test_a_weight_averaged_protocol_has_runs_of_its_own_each_keeping_an_average(tmp_path):
    result, _ = regenerate(tmp_path, "protocol", PROTOCOL_LAYOUTS="8", PROTOCOL_EMA_DECAY="0.99")
    work = tmp_path / "work"
    assert result.returncode == 0, result.stderr
    families = ("", "_semantic_ray", "_neuray", "_mvsnerf")
    trained = {f"layouts_n8_ema{f}_s{s}" for f in families for s in range(3)}
    done = {p.name for p in (work / "done").iterdir()}
    assert done == trained | {f"finetune_{run}" for run in trained}  # none shared with the layouts curve's runs
    for run in trained:
        arguments = (work / "logs" / f"{run}.log").read_text()
        assert " train.ema_decay=0.99 " in arguments and "dataset.num_train_scenes=8 " in arguments
        assert f"checkpoint={work}/runs/{run}/checkpoints/step_0001200.pt " in (
            work / "logs" / f"finetune_{run}.log").read_text()


def test_records_copy_each_finished_runs_figures_and_the_provenance(tmp_path):
    records, work = tmp_path / "records", tmp_path / "work"
    (work / "done").mkdir(parents=True)
    for name, finished in (("id5_s0", True), ("id5_s1", True), ("half_written_s0", False)):
        (work / "runs" / name).mkdir(parents=True)
        (work / "runs" / name / "metrics.json").write_text(f'{{"name": "{name}"}}')
        (work / "runs" / name / "config.yaml").write_text(f"seed: {name[-1]}\n")
        (work / "runs" / name / "checkpoints").mkdir()
        if finished:
            (work / "done" / name).touch()
    result, journal = regenerate(tmp_path, "records", RECORDS=str(records))
    assert result.returncode == 0 and journal == [], result.stderr
    assert "records of 2 runs" in result.stdout
    assert sorted(p.name for p in (records / "runs").iterdir()) == ["id5_s0", "id5_s1"]  # not the unfinished run
    assert (records / "runs" / "id5_s1" / "metrics.json").read_text() == '{"name": "id5_s1"}'
    assert sorted(p.name for p in (records / "runs" / "id5_s0").iterdir()) == ["config.yaml", "metrics.json"]
    assert (records / "runs" / "id5_s0" / "config.yaml").read_text() == "seed: 0\n"  # no weights, nothing half-written
    (provenance,) = (records / "provenance").iterdir()
    assert ":" not in provenance.name and provenance.read_text() == (work / "provenance.txt").read_text()
    assert (work / "runs" / "id5_s0" / "metrics.json").is_file()  # copied, never moved
