#!/usr/bin/env bash
# Adaptive resolution end to end on one GPU machine (results in $OUT): BO labels (time-boxed, resumable), the
# regressor and the Fig. 4 analysis.
#   OUT=runs/res bash scripts/gpu_resolution.sh
# Env: SCENES (1024), LABEL_SECONDS (300), REPEATS (plans averaged per BO evaluation, 2).
set -uo pipefail
OUT=${OUT:-runs/res}; SCENES=${SCENES:-1024}; LABEL_SECONDS=${LABEL_SECONDS:-300}; REPEATS=${REPEATS:-2}
mkdir -p "$OUT"
timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels" --scenes "$SCENES" --batch 128 \
  --repeats "$REPEATS"
python -m experiments.train_regressor --labels "$OUT/labels" --out "$OUT/regressor"
python -m experiments.tradeoff --labels "$OUT/labels" --out "$OUT/tradeoff"
