#!/usr/bin/env bash
# Adaptive resolution end to end on one GPU machine (results in $OUT): BO labels (time-boxed, resumable), the
# regressor and the Fig. 4 analysis.
#   OUT=runs/res bash scripts/gpu_resolution.sh
# Env: SCENES (1024), LABEL_SECONDS (600), REPEATS (plans averaged per BO evaluation, 2), BUDGET (0.25 s per
# decision) and TIMING (the table that prices it, docs/budget/timing_cpu.json: a 2-core CPU's).
set -uo pipefail
OUT=${OUT:-runs/res}; SCENES=${SCENES:-1024}; LABEL_SECONDS=${LABEL_SECONDS:-600}; REPEATS=${REPEATS:-2}
BUDGET=${BUDGET:-0.25}; TIMING=${TIMING:-docs/budget/timing_cpu.json}
mkdir -p "$OUT"
timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels" --scenes "$SCENES" --batch 128 \
  --repeats "$REPEATS" --samples 50 --time-budget "$BUDGET" --timing "$TIMING"
python -m experiments.train_regressor --labels "$OUT/labels" --out "$OUT/regressor"
python -m experiments.tradeoff --labels "$OUT/labels" --out "$OUT/tradeoff"
