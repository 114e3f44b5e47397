# Shared by kill_a_rank.sh and two_nodes.sh: a tiny GP-NeRF (2 target views per step, 3 steps) on the embedded scenes,
# small enough for a 2-core CPU; gloo; one thread per process.
set -euo pipefail
PYTHON=${PYTHON:-python}
WORK=${1:-${WORK:-/tmp/gpnerf-faults}}
mkdir -p "$WORK"
export GPNERF_DISABLE_PLUGIN_AUTOLOAD=1 OMP_NUM_THREADS=1
TINY=(+head=unet +loss=dgs dataset.num_train_scenes=2 dataset.num_unseen_scenes=1 dataset.frames_per_scene=6
      dataset.eval_every=3 dataset.height=32 dataset.width=48 'model.feature_extractor.widths=[8,8,8,16]'
      model.feature_extractor.fpn_channels=4 model.field_aggregator.width=16 model.field_aggregator.num_blocks=2 model.coarse_samples=6
      model.fine_samples=2 model.num_source_views=2 train.rays=16 train.log_every=1 train.steps=3
      train.targets_per_step=2 eval.max_views_per_scene=2 eval.save_images=1 train.grad_clip=0)
now() { date +%s.%N; }
seconds() { "$PYTHON" -c "print(f'{$2 - $1:.1f}')"; }
uninterrupted() {  # one agent, two processes: the reference both scripts compare with
  rm -rf "$WORK/one"
  "$PYTHON" -m torch.distributed.run --standalone --nproc_per_node=2 -m gpnerf_core run "${TINY[@]}" \
    "out_dir=$WORK/one" > "$WORK/one.log" 2>&1
}
compare() {  # compare <run folder>: metrics and final parameters against $WORK/one
  "$PYTHON" - "$WORK/one" "$1" <<'PY'
import json, sys, torch
one, other = sys.argv[1], sys.argv[2]
strip = lambda path: {s: {k: v for k, v in d.items() if k != "timing"}
                      for s, d in json.load(open(f"{path}/metrics.json"))["eval"].items()}
a = torch.load(f"{one}/checkpoints/step_0000003.pt", weights_only=True)["model"]
b = torch.load(f"{other}/checkpoints/step_0000003.pt", weights_only=True)["model"]
print(f"metrics equal to the uninterrupted one-node run: {strip(one) == strip(other)}; final parameters identical: "
      f"{all(torch.equal(a[k], b[k]) for k in a)} (max |difference| {max(float((a[k] - b[k]).abs().max()) for k in a)})")
PY
}
