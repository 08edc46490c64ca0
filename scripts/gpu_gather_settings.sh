#!/usr/bin/env bash
# Issue 5's Gather target under different planner settings: 64 episodes at ω = 50, no budget, one directory each
# (results in $OUT/gather_M<samples>_N<steps>_T<horizon>).
#   OUT=runs/settings SETTINGS="50,100,1 100,200,1" bash scripts/gpu_gather_settings.sh
set -uo pipefail
OUT=${OUT:-runs/settings}
for s in ${SETTINGS:-50,100,1 100,200,1 200,200,1 50,100,2 100,200,2}; do
  IFS=, read -r m n t <<< "$s"
  python -m experiments.evaluate --task gather --methods 50 --samples "$m" --adam-steps "$n" \
    --horizon "$t" --out "$OUT/gather_M${m}_N${n}_T${t}" | tail -1
done
