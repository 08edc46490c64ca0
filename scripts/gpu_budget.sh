#!/usr/bin/env bash
# Resolution buckets on one GPU (results in $OUT): ms per Adam step at every ω (benchmark batch) and the anytime
# surface.
#   OUT=runs/budget PART=bench|surface bash scripts/gpu_budget.sh
# Env: PART (bench: the benchmark; surface: the surface; default both), SCENES (surface scenes per kind, 128).
set -uo pipefail
OUT=${OUT:-runs/budget}; PART=${PART:-all}; SCENES=${SCENES:-128}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ "$PART" != surface ]; then
  python -m experiments.benchmark resolution --json "$OUT/resolution.json"
fi
if [ "$PART" != bench ]; then
  python -m experiments.tradeoff --surface --scenes "$SCENES" --out "${SURFACE_DIR:-$OUT/surface}"
fi
