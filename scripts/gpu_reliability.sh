#!/usr/bin/env bash
# Label reliability on one GPU (results in $OUT): the same scenes labelled twice with independent plan seeds under
# the time budget (every ω of a scene planned from the same REPEATS keys: common random numbers), then their
# agreement (experiments.tradeoff --reliability) and Fig. 4 on the first run.
#   OUT=runs/rel bash scripts/gpu_reliability.sh
# Env: SCENES (512), REPEATS (4), SEED (21: the scenes), LABEL_SECONDS (per run, 900), BUDGET (0.25 s per decision),
# TIMING (docs/budget/timing_cpu.json), FLAGS (more label_resolution flags, e.g. --quick for a CPU dry run).
set -uo pipefail
OUT=${OUT:-runs/rel}; SCENES=${SCENES:-512}; REPEATS=${REPEATS:-4}; SEED=${SEED:-21}
LABEL_SECONDS=${LABEL_SECONDS:-900}; BUDGET=${BUDGET:-0.25}; TIMING=${TIMING:-docs/budget/timing_cpu.json}
mkdir -p "$OUT"
for plan_seed in 1 2; do
  # shellcheck disable=SC2086
  timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels_$plan_seed" --scenes "$SCENES" \
    --batch 128 --samples 50 --repeats "$REPEATS" --time-budget "$BUDGET" --timing "$TIMING" --seed "$SEED" \
    --plan-seed "$plan_seed" ${FLAGS:-} > "$OUT/labels_$plan_seed.log" 2>&1
  echo "$(date +%T) labels $plan_seed: $(tail -1 "$OUT/labels_$plan_seed.log")"
done
python -m experiments.tradeoff --reliability "$OUT/labels_1" "$OUT/labels_2" --out "$OUT/reliability" > "$OUT/reliability.log" 2>&1
python -m experiments.tradeoff --labels "$OUT/labels_1" --out "$OUT/fig4" > "$OUT/fig4.log" 2>&1
tail -3 "$OUT/reliability.log"
