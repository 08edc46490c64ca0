#!/usr/bin/env bash
# Training throughput on one GPU, paired: the trainer before issue 48 (OLD: a tree of main at c55a739, whose batches
# are gathered by NumPy on the host every step) against today's (the data resident on the device, batches drawn
# there), the same data and the shipped recipe (batch 64), one after the other; then today's at batch 1024.
#   git archive c55a739 dynres_jax experiments | (mkdir -p .old && tar -x -C .old)
#   OLD=.old bash scripts/gpu_train_speed.sh          # prints one line per trainer: its last metrics (samples_per_s)
# Env: WORK (/tmp/speed), OLD (.old), EPISODES (128 random episodes), STEPS (300).
set -uo pipefail
WORK=${WORK:-/tmp/speed}; OLD=$(realpath "${OLD:-.old}"); EPISODES=${EPISODES:-128}; STEPS=${STEPS:-300}
mkdir -p "$WORK"
python -m experiments.generate_data --out "$WORK/data" --episodes "$EPISODES" --pushes 10 --worlds 64 --seed 21 \
  --no-progress > "$WORK/data.log" 2>&1 || { tail -3 "$WORK/data.log"; exit 1; }
probe() {  # NAME TREE [FLAGS...]
  local name=$1 tree=$2; shift 2
  (cd "$tree" && python -m experiments.train_dynamics --recipe shipped --data "$WORK/data" --out "$WORK/$name" \
    --steps "$STEPS" --eval-every "$STEPS" --val-batches 1 --quiet "$@" > "$WORK/$name.log" 2>&1)
  echo "$name: $(tail -1 "$WORK/$name/metrics.jsonl" 2>/dev/null || tail -2 "$WORK/$name.log")"
}
probe old_batch64 "$OLD"
probe new_batch64 "$PWD"
probe new_batch1024 "$PWD" --batch 1024 --lr 2e-3 --warmup 15
