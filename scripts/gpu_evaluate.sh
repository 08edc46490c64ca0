#!/usr/bin/env bash
# The paper's Fig. 5 on one GPU machine (results in $OUT/eval_TASK): fixed ω, adaptive, the CNN baseline and the
# oracle on Gather and Redistribute, paired episodes, every method under one time budget priced by a saved timing
# table (docs/budget/README.md).
#   OUT=runs/eval bash scripts/gpu_evaluate.sh
# Env: TASKS (gather redistribute), EPISODES (256), BUDGET (0.25 s per decision), TIMING (docs/budget/timing_cpu.json).
set -uo pipefail
OUT=${OUT:-runs/eval}; EPISODES=${EPISODES:-256}; BUDGET=${BUDGET:-0.25}; TIMING=${TIMING:-docs/budget/timing_cpu.json}
for task in ${TASKS:-gather redistribute}; do
  python -m experiments.evaluate --task "$task" --episodes "$EPISODES" --samples 50 --adam-steps 100 \
    --time-budget "$BUDGET" --timing "$TIMING" --methods 10 25 50 75 100 adaptive cnn oracle \
    --out "$OUT/eval_$task" || exit
done
