#!/usr/bin/env bash
# Adaptive resolution end to end on one GPU machine (results in $OUT): BO labels (time-boxed,
# resumable), the regressor, the Fig. 4 analysis, and issue 5's fixed-ω Gather evaluation.
#   OUT=runs/res bash scripts/gpu_resolution.sh
# Env: SCENES (1024), LABEL_SECONDS (300).
set -uo pipefail
OUT=${OUT:-runs/res}; SCENES=${SCENES:-1024}; LABEL_SECONDS=${LABEL_SECONDS:-300}
mkdir -p "$OUT"
timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels" --scenes "$SCENES" --batch 128
python -m experiments.train_regressor --labels "$OUT/labels" --out "$OUT/regressor"
python -m experiments.tradeoff --labels "$OUT/labels" --out "$OUT/tradeoff"
python -m experiments.evaluate --task gather --methods 50 --budget 0 --samples 50 --plan-steps 100 \
  --out "$OUT/gather50"
