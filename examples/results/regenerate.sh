#!/usr/bin/env bash
# Regenerate the numbers of docs/results.md from scratch on a 2-core CPU, at one commit:
#   bash examples/results/regenerate.sh [WORK] [STAGES]      (WORK default /tmp/gpnerf-results)
# STAGES (default "table4 methods stress instance finetune report"), run in this order:
#   table4    Table 4 IDs 1-5 x seeds 0-2 (ID 5 is the main job's config)
#   methods   the chart's other methods x seeds 0-2: per-pixel head, GP-NeRF sized, GNT alone (slowest: last)
#   stress    the stress suite of IDs 1 and 5 (3 seeds each), one process per method, merged
#   instance  the instance head on layout_00 x seeds 0-2, and the connected-components baseline on ID 5's runs
#   finetune  ID 5's three runs fine-tuned on the unseen layout (300 steps)
#   report    the tables (report_*.md, summary.md: examples/results/summarize.py) and the charts (chart/, chart_methods/)
# Every training run uses threads=1 and two run at a time (on this machine type 1.0-1.6x the throughput of one
# two-thread run after another, measured on two days). A finished job leaves WORK/done/<name> and is skipped when the
# script runs again (create the marker to skip a job, delete it to redo one); an interrupted training run starts
# again (train.resume=auto: a run keeps only its final checkpoint, and a folder without one is replaced).
# Timings of runs that share the cores are comparable with each other, not with a run alone. WORK must not contain
# spaces. Figures: docs/results.md; machine and commit: WORK/provenance.txt. About 4 h on the 2-core CI machine type
# (2026-12-02: a Table 4 run's training took 560-820 s, two at a time).
set -euo pipefail
PYTHON=${PYTHON:-python}
WORK=${1:-/tmp/gpnerf-results}
STAGES=${2:-table4 methods stress instance finetune report}
PARALLEL=${PARALLEL:-2}
RUNS="$WORK/runs"
mkdir -p "$RUNS" "$WORK/logs" "$WORK/done"
export OMP_NUM_THREADS=1

{
  echo "commit $(git rev-parse HEAD 2>/dev/null || echo unknown) $(git status --porcelain 2>/dev/null | grep -qv '^??' && echo '(modified)')"
  echo "started $(date -u +%FT%TZ)"
  "$PYTHON" -c 'import platform, torch; print(platform.processor() or platform.machine(), torch.__version__)'
  grep -m1 'model name' /proc/cpuinfo 2>/dev/null || true
  echo "cores $(nproc --all 2>/dev/null || echo ?), $PARALLEL runs at a time, threads=1 each"
} >> "$WORK/provenance.txt"

CKPT=checkpoints/step_0000600.pt
SIZED=(+head=unet +loss=dgs dataset.near=0.59 dataset.far=5.696 field_aggregator.num_blocks=2 model.fine_samples=0
       model.num_source_views=3)  # the configuration `size` chose for the embedded scenes (docs/results.md, Sizing)

# One queued job per line: "<name>\t<command words>"; run_queue runs PARALLEL at a time; after a failure the stage finishes its other jobs and the script stops.
job() { local name=$1; shift; printf '%s\t%s\n' "$name" "$*"; }
run_one() {  # run_one <name> <gpnerf_core arguments>: skip if done before, log to logs/<name>.log
  local name=$1 arguments=$2
  if [[ -f "$WORK/done/$name" ]]; then echo "skip  $name (done)"; return 0; fi
  echo "start $name $(date -u +%T)"
  if eval "$PYTHON -m gpnerf_core $arguments" > "$WORK/logs/$name.log" 2>&1; then
    touch "$WORK/done/$name"; echo "done  $name $(date -u +%T)"
  else
    echo "FAILED $name: see $WORK/logs/$name.log" >&2; return 1
  fi
}
export -f run_one; export PYTHON WORK RUNS
run_queue() { tr '\n' '\0' | xargs -0 -r -n1 -P "$PARALLEL" bash -c 'run_one "${0%%$'"'\t'"'*}" "${0#*$'"'\t'"'}"'; }

train_job() {  # train_job <name> <seed> <overrides...>
  local name=$1 seed=$2; shift 2
  job "$name" run "$@" seed="$seed" threads=1 train.resume=auto "out_dir=$RUNS/$name"
}

for stage in $STAGES; do
  echo "== $stage $(date -u +%T)"
  case $stage in
    table4)
      for id in 1 2 3 4 5; do for s in 0 1 2; do train_job "id${id}_s$s" $s +experiment=table4_id$id; done; done | run_queue ;;
    methods)
      { for s in 0 1 2; do train_job "label_rendering_s$s" $s +experiment=baselines/label_rendering; done
        for s in 0 1 2; do train_job "sized_s$s" $s "${SIZED[@]}"; done
        for s in 0 1 2; do train_job "gnt_s$s" $s +experiment=baselines/gnt; done; } | run_queue ;;
    stress)
      { job stress_id1 stress "$RUNS"/id1_s{0,1,2} --views-per-scene 1 --threads 1 --overwrite --out "$WORK/stress/id1"
        job stress_id5 stress "$RUNS"/id5_s{0,1,2} --views-per-scene 1 --threads 1 --overwrite --out "$WORK/stress/id5"
      } | run_queue ;;
    instance)
      { for s in 0 1 2; do train_job "instance_l0_s$s" $s +experiment=instance "'dataset.scenes=[layout_00]'"; done
        for s in 0 1 2; do job "cc_l0_id5_s$s" eval "checkpoint=$RUNS/id5_s$s/$CKPT" "'dataset.scenes=[layout_00]'" \
          "'eval.splits=[train]'" threads=1 "out_dir=$RUNS/cc_l0_id5_s$s"; done; } | run_queue ;;
    finetune)
      for s in 0 1 2; do job "finetune_id5_s$s" finetune "checkpoint=$RUNS/id5_s$s/$CKPT" "'dataset.scenes=[unseen_00]'" \
        train.steps=300 finetune.points=4 eval.save_images=0 threads=1 "out_dir=$RUNS/finetune_id5_s$s"; done | run_queue ;;
    report)
      existing() { local path; for path in "$@"; do [[ -f "$path/metrics.json" ]] && echo "$path"; done; return 0; }
      mapfile -t table4_runs < <(existing "$RUNS"/id?_s?)
      mapfile -t instance_runs < <(existing "$RUNS"/instance_l0_s?)
      mapfile -t method_runs < <(existing "$RUNS"/id5_s? "$RUNS"/label_rendering_s? "$RUNS"/sized_s? "$RUNS"/gnt_s?)
      "$PYTHON" -m gpnerf_core report "${table4_runs[@]}" > "$WORK/report_table4.md"
      "$PYTHON" -m gpnerf_core report "${table4_runs[@]}" "${instance_runs[@]}" --chart "$WORK/chart" > "$WORK/report_chart.md"
      "$PYTHON" -m gpnerf_core report "${method_runs[@]}" --chart "$WORK/chart_methods" > "$WORK/report_methods.md"
      "$PYTHON" "$(dirname "$0")/summarize.py" "$WORK" > "$WORK/summary.md"
      if [[ -d "$WORK/stress/id1" && -d "$WORK/stress/id5" ]]; then
        "$PYTHON" -m gpnerf_core stress --merge "$WORK/stress/id1" "$WORK/stress/id5" --overwrite --out "$WORK/stress/merged"
      fi ;;
    *) echo "unknown stage '$stage' (known: table4 methods stress instance finetune report)" >&2; exit 2 ;;
  esac
done
echo "finished $(date -u +%FT%TZ)" >> "$WORK/provenance.txt"
