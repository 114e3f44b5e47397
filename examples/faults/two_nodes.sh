#!/usr/bin/env bash
# Two torchrun agents on this machine as two nodes (c10d rendezvous on localhost, one process each) against one agent
# with two processes: wall time of each, and the parameters after training.
#   bash examples/faults/two_nodes.sh [work folder]        (PYTHON=.venv/bin/python from the repository root)
source "$(dirname "$0")/common.sh"
started=$(now); uninterrupted; echo "one node x 2 processes: $(seconds "$started" "$(now)") s"
rm -rf "$WORK/two"
port=$("$PYTHON" -c "import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")
started=$(now)
for node in 0 1; do
  "$PYTHON" -m torch.distributed.run --nnodes=2 --node-rank=$node --nproc-per-node=1 --rdzv-backend=c10d \
    "--rdzv-endpoint=127.0.0.1:$port" --rdzv-id=two-nodes -m gpnerf_core run "${TINY[@]}" "out_dir=$WORK/two" \
    > "$WORK/two_$node.log" 2>&1 &
done
wait
echo "two nodes x 1 process: $(seconds "$started" "$(now)") s"
compare "$WORK/two"
