#!/usr/bin/env bash
# The paper's Fig. 5 on one GPU machine: fixed ω and adaptive on Gather and Redistribute, 64 episodes each, with the
# shipped dynamics and regressor (results in $OUT/eval_TASK).
#   OUT=runs/eval bash scripts/gpu_evaluate.sh
set -uo pipefail
OUT=${OUT:-runs/eval}
for task in ${TASKS:-gather redistribute}; do
  python -m experiments.evaluate --task "$task" --episodes 64 --out "$OUT/eval_$task" || exit
done
