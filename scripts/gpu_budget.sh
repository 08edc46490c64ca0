#!/usr/bin/env bash
# Resolution buckets on one GPU (results in $OUT): the planner step before and after buckets (A/B of two code
# versions), ms per Adam step at every ω (benchmark batch), and the anytime surface.
#   OUT=runs/budget BASE=<rev> PART=bench|surface bash scripts/gpu_budget.sh
# Env: BASE (the revision to compare the working tree with), PART (bench: the two benchmarks; surface: the surface;
# default both), SCENES (surface scenes per kind, 128).
set -uo pipefail
OUT=${OUT:-runs/budget}; BASE=${BASE:-HEAD}; PART=${PART:-all}; SCENES=${SCENES:-128}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ "$PART" != surface ]; then
  python scripts/ab_planner.py "$BASE" WORKTREE --rounds 2 --json "$OUT/ab_planner.json"
  python -m experiments.benchmark resolution --json "$OUT/resolution.json"
fi
if [ "$PART" != bench ]; then
  python -m experiments.tradeoff --surface --scenes "$SCENES" --out "${SURFACE_DIR:-$OUT/surface}"
fi
