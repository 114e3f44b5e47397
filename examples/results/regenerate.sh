#!/usr/bin/env bash
# Regenerate docs/results_detail.md's numbers (headline: docs/results.md) from scratch on a 2-core CPU, at one commit:
#   bash examples/results/regenerate.sh [WORK] [STAGES]      (WORK default /tmp/gpnerf-results)
# STAGES (default "table4 methods baselines grid samplers per_scene stress instance finetune report"):
#   table4    Table 4 IDs 1-5 x seeds 0-2 (ID 5 is the main job's config)
#   methods   the chart's other methods x seeds 0-2: per-pixel head, GP-NeRF sized, GNT alone
#   baselines the compared methods' families x seeds 0-2: Semantic-Ray, NeuRay + semantic head, MVSNeRF + semantic
#             head (+experiment=baselines/<name>), on the main job's data and steps; each run fine-tuned on the unseen
#             layout as ID 5's (finetune stage), and each family's stress suite
#   grid      the same families with GP-NeRF's context-aware decoding (baselines/<name>_unet), seed 0
#   gaussians MVSplat's feed-forward Gaussians both ways (baselines/mvsplat: label rendering; baselines/mvsplat_unet:
#             GP-NeRF's decoding) x seeds 0-2 on the main job's data and steps, each fine-tuned on the unseen layout as
#             ID 5's (300 steps), and each variant's stress suite (not in the default stages)
#   samplers  the main job's config with model.sampler=depth, its depth from the coarse pass and from the two depth
#             sources (+depth_source=cost_volume, source_depth: one pass on 8 samples) x seeds 0-2 (uniform: ID 5)
#   layouts   GP-NeRF (the main job's config) trained on 4, 8, 16, 32 layouts, 150 steps per layout (600 at 4, the main
#             job's), scored on 4 unseen layouts (3 views each) and 3 held-out views per training layout, seeds 0-2:
#             the curve that picks the generalized protocol's layout count (not in the default stages: seeds 1-2 of
#             4, 8 and 32 took 1 h 23 min here; its 16-layout runs are the protocol stage's GP-NeRF runs)
#   protocol  Table 1 on the generalized protocol: GP-NeRF and the three compared families x seeds 0-2 trained on
#             PROTOCOL_LAYOUTS layouts (default 16, 150 steps per layout, 4 unseen layouts, 3 views a scene; GP-NeRF's
#             runs are the layouts stage's of that count), each fine-tuned 300 steps on unseen_00 (not in the default
#             stages: 2 h 35 min on 2026-12-04 with the 16-layout seed 0 done). PROTOCOL_EMA_DECAY=0.99: every run
#             keeps a weight average, is scored with it and fine-tuned from it, runs layouts_n<count>_ema[_<family>]_s<seed>
#             (GP-NeRF's too: the layouts stage keeps none); PROTOCOL_FAMILIES (default "semantic_ray neuray mvsnerf")
#             names the compared families (e.g. "mvsplat_unet"); at 32 layouts seed 0's four runs and their fine-tuning
#             took 2 h here (2026-12-04), evaluation included (108 frames a run: 3-12 min)
#   per_scene the per-scene families x seeds 0-2: Semantic-NeRF fitted from scratch on the unseen layout's training
#             frames (evaluated every 500 of its 2000 steps: against ID 5 zero-shot and fine-tuned, the finetune stage;
#             and one 8000-step run, seed 0, evaluated every 1000), its grid option (baselines/semantic_nerf_grid,
#             evaluated every 250 of 2000 steps), DM-NeRF on layout_00 (against the instance stage's head)
#   per_scene_gaussians  per-scene semantic 3D Gaussian splatting (baselines/semantic_3dgs) and Semantic-NeRF's grid
#             option on unseen_00 x seeds 0-2, 2000 steps each evaluated every 250, each seed's two runs side by side
#             (the same job names as per_scene's grid runs), and the 3DGS stress suite (not in the default stages)
#   gaussian_grouping  the third-party Gaussian Grouping family (examples/gpnerf-gaussian-grouping, installed first)
#             on layout_00 x seeds 0-2, 2000 steps, its instances against DM-NeRF and the instance head; its stress
#             suite (not in the default stages)
#   mask_rcnn Table 2's 2D rows: Mask R-CNN and its Swin-T variant (baselines/mask_rcnn, mask_rcnn_swin_t) fitted on
#             layout_00 x seeds 0-2, 2000 steps each, scoring the real held-out frames (not in the default stages)
#   stress    the stress suite of IDs 1 and 5 (3 seeds each), one process per method, merged   (needs table4's runs)
#   instance  the instance head on layout_00 x seeds 0-2, and the connected-components baseline on ID 5's runs
#   finetune  ID 5's three runs fine-tuned on the unseen layout (300 steps)                      (needs table4's runs)
#   report    the tables (report_*.md, summary.md: examples/results/summarize.py) and the charts (chart/, chart_methods/,
#             chart_baselines/, chart_protocol_<n16|n32_ema|...>/, chart_samplers/, chart_per_scene/)
#   records   every finished run's metrics.json and config.yaml (no weights) and WORK/provenance.txt copied into
#             RECORDS (default examples/results/records, beside this script) to commit: WORK does not outlive its
#             machine; `python examples/results/summarize.py RECORDS` tables the records (seeds of other days too)
# The jobs of every stage asked for form one queue, PARALLEL (2) at a time, so no core idles between stages: jobs
# that need no other job first, then those that do, each waiting for the runs it needs (WORK/done markers). After a
# failure the queue goes on (a job needing the failed one fails at once) and the script exits 1 before the report.
# Every training run uses threads=1 (two at a time: on this machine type 1.0-1.6x the throughput of one two-thread run
# after another, measured on two days). A finished job leaves WORK/done/<name> and is skipped when the script runs
# again (create the marker to skip a job, delete it to redo one); an interrupted training run starts again
# (train.resume=auto: a run keeps only its final checkpoint, and a folder without one is replaced).
# Timings of runs that share the cores are comparable with each other, not with a run alone. WORK must not contain
# spaces. Figures: docs/results_detail.md; machine and commit: WORK/provenance.txt. About 5 h on the 2-core CI machine type
# (2026-12-02: a Table 4 run's training took 560-820 s, two at a time).
set -euo pipefail
PYTHON=${PYTHON:-python}
WORK=${1:-/tmp/gpnerf-results}
STAGES=${2:-table4 methods baselines grid samplers per_scene stress instance finetune report}
PARALLEL=${PARALLEL:-2}
PROTOCOL_LAYOUTS=${PROTOCOL_LAYOUTS:-16}  # the protocol's training layouts: seed 0's choice (3 seeds favour 32)
PROTOCOL_EMA_DECAY=${PROTOCOL_EMA_DECAY:-}  # set (e.g. 0.99): every protocol run keeps a weight average, scored with it
PROTOCOL_FAMILIES=${PROTOCOL_FAMILIES:-semantic_ray neuray mvsnerf}  # the compared families beside GP-NeRF's runs
RECORDS=${RECORDS:-$(cd "$(dirname "$0")" && pwd)/records}
POLL_SECONDS=${POLL_SECONDS:-10}
RUNS="$WORK/runs"
KNOWN="table4 methods baselines grid gaussians samplers per_scene per_scene_gaussians gaussian_grouping mask_rcnn layouts protocol stress instance finetune report records"
for stage in $STAGES; do
  [[ " $KNOWN " == *" $stage "* ]] || { echo "unknown stage '$stage' (known: $KNOWN)" >&2; exit 2; }
done
mkdir -p "$RUNS" "$WORK/logs" "$WORK/done"
rm -rf "$WORK/failed" && mkdir "$WORK/failed"  # failures of an earlier invocation are retried
export OMP_NUM_THREADS=1

{
  echo "commit $(git rev-parse HEAD 2>/dev/null || echo unknown) $(git status --porcelain 2>/dev/null | grep -qv '^??' && echo '(modified)')"
  echo "started $(date -u +%FT%TZ) stages: $STAGES"
  "$PYTHON" -c 'import platform, torch; print(platform.processor() or platform.machine(), torch.__version__)'
  grep -m1 'model name' /proc/cpuinfo 2>/dev/null || true
  echo "cores $(nproc --all 2>/dev/null || echo ?), $PARALLEL runs at a time, threads=1 each"
} >> "$WORK/provenance.txt"

CKPT=checkpoints/step_0000600.pt
SIZED=(+head=unet +loss=dgs dataset.near=0.59 dataset.far=5.696 model.field_aggregator.num_blocks=2 model.fine_samples=0
       model.num_source_views=3)  # the configuration `size` chose for the embedded scenes (docs/results_detail.md, Sizing)

# One queued job per line: "<name>\t<needed jobs, comma-separated, or ->\t<gpnerf_core arguments>".
job() { local name=$1 needs=$2; shift 2; printf '%s\t%s\t%s\n' "$name" "$needs" "$*"; }
train_job() {  # train_job <name> <seed> <overrides...>
  local name=$1 seed=$2; shift 2
  job "$name" - run "$@" seed="$seed" threads=1 train.resume=auto "out_dir=$RUNS/$name"
}
protocol_tag() {  # the protocol's runs are layouts_<tag>[_<family>]_s<seed>: n<count>, then _ema with a weight average
  echo "n$PROTOCOL_LAYOUTS${PROTOCOL_EMA_DECAY:+_ema}"
}
stage_jobs() {
  case $1 in
    table4)
      for id in 1 2 3 4 5; do for s in 0 1 2; do train_job "id${id}_s$s" $s +experiment=table4_id$id; done; done ;;
    methods)
      for s in 0 1 2; do train_job "label_rendering_s$s" $s +experiment=baselines/label_rendering; done
      for s in 0 1 2; do train_job "sized_s$s" $s "${SIZED[@]}"; done
      for s in 0 1 2; do train_job "gnt_s$s" $s +experiment=baselines/gnt; done ;;
    baselines)
      for s in 0 1 2; do for family in semantic_ray neuray mvsnerf; do
        train_job "${family}_s$s" $s +experiment=baselines/$family eval.save_images=0
      done; done
      for family in semantic_ray neuray mvsnerf; do
        for s in 0 1 2; do job "finetune_${family}_s$s" "${family}_s$s" finetune "checkpoint=$RUNS/${family}_s$s/$CKPT" \
          "'dataset.scenes=[unseen_00]'" train.steps=300 finetune.points=4 eval.save_images=0 threads=1 \
          "out_dir=$RUNS/finetune_${family}_s$s"; done
        job "stress_$family" "${family}_s0,${family}_s1,${family}_s2" stress "$RUNS"/${family}_s{0,1,2} \
          --views-per-scene 1 --threads 1 --overwrite --out "$WORK/stress/$family"
      done ;;
    grid)
      for family in semantic_ray neuray mvsnerf; do
        train_job "${family}_unet_s0" 0 +experiment=baselines/${family}_unet eval.save_images=0
      done ;;
    gaussians)
      for s in 0 1 2; do for family in mvsplat mvsplat_unet; do
        train_job "${family}_s$s" $s +experiment=baselines/$family eval.save_images=0
      done; done
      for family in mvsplat mvsplat_unet; do
        for s in 0 1 2; do job "finetune_${family}_s$s" "${family}_s$s" finetune "checkpoint=$RUNS/${family}_s$s/$CKPT" \
          "'dataset.scenes=[unseen_00]'" train.steps=300 finetune.points=4 eval.save_images=0 threads=1 \
          "out_dir=$RUNS/finetune_${family}_s$s"; done
        job "stress_$family" "${family}_s0,${family}_s1,${family}_s2" stress "$RUNS"/${family}_s{0,1,2} \
          --views-per-scene 1 --threads 1 --overwrite --out "$WORK/stress/$family"
      done ;;
    samplers)
      for s in 0 1 2; do
        train_job "sampler_first_pass_s$s" $s +head=unet +loss=dgs model.sampler=depth eval.save_images=0
        for source in cost_volume source_depth; do
          train_job "sampler_${source}_s$s" $s +head=unet +loss=dgs model.sampler=depth +depth_source=$source \
            eval.save_images=0
        done
      done ;;
    per_scene_gaussians)
      for s in 0 1 2; do
        train_job "semantic_nerf_grid_unseen_s$s" $s +experiment=baselines/semantic_nerf_grid \
          "'dataset.scenes=[unseen_00]'" eval.every_steps=250 eval.save_images=0
        train_job "semantic_3dgs_unseen_s$s" $s +experiment=baselines/semantic_3dgs "'dataset.scenes=[unseen_00]'" \
          eval.every_steps=250 eval.save_images=0
      done
      job stress_semantic_3dgs "semantic_3dgs_unseen_s0,semantic_3dgs_unseen_s1,semantic_3dgs_unseen_s2" stress \
        "$RUNS"/semantic_3dgs_unseen_s{0,1,2} --views-per-scene 1 --threads 1 --overwrite --out "$WORK/stress/semantic_3dgs" ;;
    gaussian_grouping)  # pip install --no-deps --no-build-isolation examples/gpnerf-gaussian-grouping first
      for s in 0 1 2; do
        train_job "gaussian_grouping_l0_s$s" $s +experiment=gaussian_grouping "'dataset.scenes=[layout_00]'" \
          eval.save_images=0
      done
      job stress_gaussian_grouping "gaussian_grouping_l0_s0,gaussian_grouping_l0_s1,gaussian_grouping_l0_s2" stress \
        "$RUNS"/gaussian_grouping_l0_s{0,1,2} --views-per-scene 1 --threads 1 --overwrite \
        --out "$WORK/stress/gaussian_grouping" ;;
    mask_rcnn)
      for s in 0 1 2; do
        train_job "mask_rcnn_l0_s$s" $s +experiment=baselines/mask_rcnn "'dataset.scenes=[layout_00]'" eval.save_images=0
        train_job "mask_rcnn_swin_t_l0_s$s" $s +experiment=baselines/mask_rcnn_swin_t "'dataset.scenes=[layout_00]'" \
          eval.save_images=0
      done ;;
    per_scene)
      for s in 0 1 2; do
        train_job "semantic_nerf_unseen_s$s" $s +experiment=baselines/semantic_nerf "'dataset.scenes=[unseen_00]'" \
          eval.every_steps=500 eval.save_images=0
        train_job "dm_nerf_l0_s$s" $s +experiment=baselines/dm_nerf "'dataset.scenes=[layout_00]'" eval.save_images=0
        train_job "semantic_nerf_grid_unseen_s$s" $s +experiment=baselines/semantic_nerf_grid \
          "'dataset.scenes=[unseen_00]'" eval.every_steps=250 eval.save_images=0
      done
      train_job semantic_nerf_unseen_8k_s0 0 +experiment=baselines/semantic_nerf "'dataset.scenes=[unseen_00]'" \
        train.steps=8000 eval.every_steps=1000 eval.save_images=0 ;;
    layouts)
      for n in 32 16 8 4; do for s in 0 1 2; do  # longest first: a 32-layout run takes as long as the other three
        train_job "layouts_n${n}_s$s" $s +head=unet +loss=dgs dataset.num_train_scenes=$n dataset.num_unseen_scenes=4 \
          train.steps=$((150 * n)) eval.max_views_per_scene=3 eval.save_images=0
      done; done ;;
    protocol)  # without a weight average GP-NeRF's runs are the layouts stage's of the same count (one job, one name)
      local n=$PROTOCOL_LAYOUTS steps=$((150 * PROTOCOL_LAYOUTS)) tag family s
      tag=$(protocol_tag)
      local data=(dataset.num_train_scenes=$n dataset.num_unseen_scenes=4 train.steps=$steps eval.max_views_per_scene=3
                  eval.save_images=0 ${PROTOCOL_EMA_DECAY:+train.ema_decay=$PROTOCOL_EMA_DECAY})
      local ckpt=checkpoints/step_$(printf %07d $steps).pt
      for s in 0 1 2; do
        train_job "layouts_${tag}_s$s" $s +head=unet +loss=dgs "${data[@]}"
        for family in $PROTOCOL_FAMILIES; do
          train_job "layouts_${tag}_${family}_s$s" $s +experiment=baselines/$family "${data[@]}"
        done
      done
      for s in 0 1 2; do for family in "" $(printf ' _%s' $PROTOCOL_FAMILIES); do
        job "finetune_layouts_${tag}${family}_s$s" "layouts_${tag}${family}_s$s" finetune \
          "checkpoint=$RUNS/layouts_${tag}${family}_s$s/$ckpt" "'dataset.scenes=[unseen_00]'" train.steps=300 \
          finetune.points=4 eval.save_images=0 threads=1 "out_dir=$RUNS/finetune_layouts_${tag}${family}_s$s"
      done; done ;;
    stress)
      for id in 1 5; do
        job "stress_id$id" "id${id}_s0,id${id}_s1,id${id}_s2" stress "$RUNS"/id${id}_s{0,1,2} --views-per-scene 1 \
          --threads 1 --overwrite --out "$WORK/stress/id$id"
      done ;;
    instance)
      for s in 0 1 2; do train_job "instance_l0_s$s" $s +experiment=instance "'dataset.scenes=[layout_00]'"; done
      for s in 0 1 2; do job "cc_l0_id5_s$s" "id5_s$s" eval "checkpoint=$RUNS/id5_s$s/$CKPT" "'dataset.scenes=[layout_00]'" \
        "'eval.splits=[train]'" threads=1 "out_dir=$RUNS/cc_l0_id5_s$s"; done ;;
    finetune)
      for s in 0 1 2; do job "finetune_id5_s$s" "id5_s$s" finetune "checkpoint=$RUNS/id5_s$s/$CKPT" \
        "'dataset.scenes=[unseen_00]'" train.steps=300 finetune.points=4 eval.save_images=0 threads=1 \
        "out_dir=$RUNS/finetune_id5_s$s"; done ;;
  esac
}

run_one() {  # run_one <name> <needs> <arguments>: skip if done, wait for what it needs, log to logs/<name>.log
  local name=$1 needs=$2 arguments=$3 need
  if [[ -f "$WORK/done/$name" ]]; then echo "skip  $name (done)"; return 0; fi
  for need in ${needs//,/ }; do
    [[ $need == - ]] && continue
    while [[ ! -f "$WORK/done/$need" ]]; do
      if [[ -f "$WORK/failed/$need" ]] || ! grep -qx "$need" "$WORK/queued"; then
        echo "needs $need, which failed or is neither done nor queued" > "$WORK/failed/$name"
        echo "FAILED $name: it needs $need, which failed or is neither done nor in the stages asked for" >&2
        return 1
      fi
      sleep "$POLL_SECONDS"
    done
  done
  echo "start $name $(date -u +%T)"
  if eval "$PYTHON -m gpnerf_core $arguments" > "$WORK/logs/$name.log" 2>&1; then
    touch "$WORK/done/$name"; echo "done  $name $(date -u +%T)"
  else
    touch "$WORK/failed/$name"; echo "FAILED $name: see $WORK/logs/$name.log" >&2; return 1
  fi
}
export -f run_one; export PYTHON WORK POLL_SECONDS

queue=$(for stage in $STAGES; do stage_jobs "$stage"; done)
if [[ -n $queue ]]; then
  # Jobs that need nothing first (stable order), then those that wait for other jobs' runs; a job two stages share
  # (the protocol's GP-NeRF runs are layouts runs) once.
  queue=$(awk -F'\t' '!seen[$1]++' <<< "$queue")
  queue=$(awk -F'\t' '$2 == "-"' <<< "$queue"; awk -F'\t' '$2 != "-"' <<< "$queue")
  cut -f1 <<< "$queue" > "$WORK/queued"
  echo "== $(wc -l < "$WORK/queued") jobs, $PARALLEL at a time $(date -u +%T)"
  if ! tr '\n' '\0' <<< "$queue" | xargs -0 -r -n1 -P "$PARALLEL" bash -c \
      'IFS=$'"'\t'"' read -r name needs arguments <<< "$0"; run_one "$name" "$needs" "$arguments"'; then
    echo "failed: $(ls "$WORK/failed" | tr '\n' ' ')(logs in $WORK/logs); no report" >&2
    exit 1
  fi
fi

if [[ " $STAGES " == *" report "* ]]; then
  echo "== report $(date -u +%T)"
  existing() { local path; for path in "$@"; do [[ -f "$path/metrics.json" ]] && echo "$path"; done; return 0; }
  mapfile -t table4_runs < <(existing "$RUNS"/id?_s?)
  mapfile -t instance_runs < <(existing "$RUNS"/instance_l0_s?)
  mapfile -t method_runs < <(existing "$RUNS"/id5_s? "$RUNS"/label_rendering_s? "$RUNS"/sized_s? "$RUNS"/gnt_s?)
  "$PYTHON" -m gpnerf_core report "${table4_runs[@]}" > "$WORK/report_table4.md"
  "$PYTHON" -m gpnerf_core report "${table4_runs[@]}" "${instance_runs[@]}" --chart "$WORK/chart" > "$WORK/report_chart.md"
  "$PYTHON" -m gpnerf_core report "${method_runs[@]}" --chart "$WORK/chart_methods" > "$WORK/report_methods.md"
  mapfile -t baseline_runs < <(existing "$RUNS"/id5_s? "$RUNS"/{semantic_ray,neuray,mvsnerf,mvsplat,mvsplat_unet}_s?)
  if (( ${#baseline_runs[@]} )); then  # Table 1's generalization rows beside the paper's, and their chart
    "$PYTHON" -m gpnerf_core report "${baseline_runs[@]}" --chart "$WORK/chart_baselines" > "$WORK/report_baselines.md"
  fi
  tag=$(protocol_tag)
  mapfile -t protocol_runs < <(for family in "" $(printf ' _%s' $PROTOCOL_FAMILIES); do
    existing "$RUNS"/{,finetune_}layouts_$tag${family}_s?; done)
  if (( ${#protocol_runs[@]} )); then  # Table 1's rows (both settings) on the generalized protocol, and their chart
    "$PYTHON" -m gpnerf_core report "${protocol_runs[@]}" --chart "$WORK/chart_protocol_$tag" \
      > "$WORK/report_protocol_$tag.md"
  fi
  mapfile -t sampler_runs < <(existing "$RUNS"/id5_s? "$RUNS"/sampler_*_s?)
  if (( ${#sampler_runs[@]} )); then  # where the samples go: accuracy against render time
    "$PYTHON" -m gpnerf_core report "${sampler_runs[@]}" --chart "$WORK/chart_samplers" > "$WORK/report_samplers.md"
  fi
  mapfile -t per_scene_runs < <(existing "$RUNS"/finetune_id5_s? "$RUNS"/semantic_nerf{,_grid}_unseen_s?)
  if (( ${#per_scene_runs[@]} )); then  # Table 1's per-scene row beside the paper's, GP-NeRF fine-tuned beside it
    "$PYTHON" -m gpnerf_core report "${per_scene_runs[@]}" --chart "$WORK/chart_per_scene" > "$WORK/report_per_scene.md"
  fi
  "$PYTHON" "$(dirname "$0")/summarize.py" "$WORK" > "$WORK/summary.md"
  if [[ -d "$WORK/stress/id1" && -d "$WORK/stress/id5" ]]; then
    "$PYTHON" -m gpnerf_core stress --merge "$WORK/stress/id1" "$WORK/stress/id5" --overwrite --out "$WORK/stress/merged"
  fi
fi
echo "finished $(date -u +%FT%TZ)" >> "$WORK/provenance.txt"

if [[ " $STAGES " == *" records "* ]]; then  # finished runs only (a done marker and a metrics.json), each written whole
  echo "== records -> $RECORDS $(date -u +%T)"
  for metrics in "$RUNS"/*/metrics.json; do
    name=$(basename "$(dirname "$metrics")")
    [[ -f $metrics && -f "$WORK/done/$name" ]] || continue
    mkdir -p "$RECORDS/runs/$name"
    for file in config.yaml metrics.json; do  # metrics.json last: with it the record is whole (`report` reads both)
      [[ -f "$RUNS/$name/$file" ]] || continue
      cp "$RUNS/$name/$file" "$RECORDS/runs/$name/.$file.partial"
      mv "$RECORDS/runs/$name/.$file.partial" "$RECORDS/runs/$name/$file"
    done
  done
  started=$(sed -n 's/^started \([^ ]*\) .*/\1/p' "$WORK/provenance.txt" | head -1 | tr -d :)
  mkdir -p "$RECORDS/provenance"
  cp "$WORK/provenance.txt" "$RECORDS/provenance/.partial"
  mv "$RECORDS/provenance/.partial" "$RECORDS/provenance/$started.txt"
  echo "records of $(ls "$RECORDS/runs" | wc -l) runs in $RECORDS (commit them)"
fi
