#!/usr/bin/env bash
# Kill one worker of a torchrun job with SIGKILL after its first checkpoint; torchrun --max-restarts=1 restarts the
# group, train.resume=auto continues from the newest checkpoint, and the run ends as the uninterrupted one.
#   bash examples/faults/kill_a_rank.sh [work folder]      (PYTHON=.venv/bin/python from the repository root)
source "$(dirname "$0")/common.sh"
uninterrupted
rm -rf "$WORK/killed"
"$PYTHON" -m torch.distributed.run --standalone --nproc_per_node=2 --max-restarts=1 --monitor-interval=0.2 \
  -m gpnerf_core run "${TINY[@]}" train.checkpoint_every=1 train.resume=auto "out_dir=$WORK/killed" \
  > "$WORK/killed.log" 2>&1 &
agent=$!
until [ -f "$WORK/killed/checkpoints/step_0000001.pt" ]; do sleep 0.02; done
for pid in $(pgrep -P "$agent"); do
  if tr '\0' '\n' < "/proc/$pid/environ" | grep -qx 'RANK=1'; then
    kill -9 "$pid"; killed=$(now)
    echo "SIGKILL to rank 1 (pid $pid); checkpoints then: $(ls "$WORK/killed/checkpoints" | tr '\n' ' ')"
  fi
done
until grep -q "resuming from" "$WORK/killed.log"; do sleep 0.02; done
echo "restart: $(seconds "$killed" "$(now)") s from the kill to the restarted group's resume: $(grep -o 'resuming from .*' "$WORK/killed.log")"
wait "$agent"
compare "$WORK/killed"
