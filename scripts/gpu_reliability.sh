#!/usr/bin/env bash
# Label reliability on one GPU (results in $OUT): the same scenes labelled twice with independent plan seeds under
# the time budget, then their agreement (experiments.tradeoff --reliability).
#   OUT=runs/rel bash scripts/gpu_reliability.sh
# Env: SCENES (256), LABEL_SECONDS (per run, 260), BUDGET (0.25 s per decision), TIMING (docs/budget/timing_cpu.json).
set -uo pipefail
OUT=${OUT:-runs/rel}; SCENES=${SCENES:-256}; LABEL_SECONDS=${LABEL_SECONDS:-260}; BUDGET=${BUDGET:-0.25}
TIMING=${TIMING:-docs/budget/timing_cpu.json}
mkdir -p "$OUT"
for seed in 1 2; do
  timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels_$seed" --scenes "$SCENES" \
    --batch 128 --samples 50 --time-budget "$BUDGET" --timing "$TIMING" --plan-seed "$seed"
done
python -m experiments.tradeoff --reliability "$OUT/labels_1" "$OUT/labels_2" --out "$OUT"
python -m experiments.tradeoff --labels "$OUT/labels_1" --out "$OUT/fig4"
