#!/usr/bin/env bash
# Issue 51 item 3's next step, where Fig. 5 in the authors' setting showed an ω effect (1 s, Gather;
# docs/reference_planner): BO labels made in that setting, the regressor g trained on them, and adaptive ω against
# the fixed ω, the oracle and best-of-5 on fresh seeds, on every GPU of one host:
#   OUT=/root/refadapt bash scripts/gpu_reference_adaptive.sh
# Stages (STAGES, each skipped when done, each resumable): labels (a jax.distributed job of PER_GPU processes a GPU,
# time-boxed by LABEL_SECONDS), retest (the first RETEST_SCENES scenes labelled again with another plan seed, and their
# agreement: tradeoff --reliability), regressor (one process on every GPU), evaluate (scripts/gpu_fig5_reference.sh
# with METHODS and the new regressor). $OUT/results.tar.gz (no labels) after every stage.
# Env: OUT, BUDGET (1), PER_GPU (2), LABEL_SECONDS (600), LABEL_FLAGS ("--scenes 1024 --batch 32 --repeats 2
# --samples 50 --adam-steps 200"),
# LABEL_SEED (61000), RETEST_SCENES (512), RETEST_PLAN_SEED (62000), REGRESSOR_FLAGS (""), EPISODES (256),
# SEED (52000: fresh), TASKS ("gather redistribute"), METHODS ("adaptive oracle best5 25 50"),
# PLANNER ("--resamples 1"), STAGES ("labels retest regressor evaluate").
# A CPU dry run: GPUS=1 PER_GPU=1 LABEL_FLAGS="--scenes 8 --batch 4 --evals 6 --repeats 1 --pieces 60 --samples 4
# --adam-steps 4" RETEST_SCENES=4 REGRESSOR_FLAGS="--steps 5 --batch 4 --width 4"
# EPISODES=2 TASKS=gather METHODS="adaptive 25" EVAL_FLAGS="--quick --mpc-steps 1".
set -uo pipefail
OUT=${OUT:-/root/refadapt}; BUDGET=${BUDGET:-1}; PER_GPU=${PER_GPU:-2}; LABEL_SECONDS=${LABEL_SECONDS:-600}
LABEL_FLAGS=${LABEL_FLAGS:-"--scenes 1024 --batch 32 --repeats 2 --samples 50 --adam-steps 200"}; LABEL_SEED=${LABEL_SEED:-61000}
STAGES=${STAGES:-"labels retest regressor evaluate"}; PLANNER=${PLANNER:-"--resamples 1"}
# shellcheck source=scripts/gpu_job.sh
. "$(dirname "$0")/gpu_job.sh"
mkdir -p "$OUT/logs"
stage() { [[ " $STAGES " == *" $1 "* ]]; }
pack() { tar -czf "$OUT/results.tmp" -C "$OUT" --exclude results.tar.gz --exclude results.tmp --exclude labels \
           --exclude labels_retest --exclude parts . 2>/dev/null; mv "$OUT/results.tmp" "$OUT/results.tar.gz"; }
if stage labels && [ ! -f "$OUT/labels/summary.json" ]; then
  echo "$(date +%T) labels: $n processes on $gpus GPUs, at most $LABEL_SECONDS s"
  # shellcheck disable=SC2086
  job "$OUT/logs/labels" timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels" \
    --reference-planner $PLANNER --time-budget "$BUDGET" --seed "$LABEL_SEED" --workers "$workers" $LABEL_FLAGS
  shards=$(ls "$OUT"/labels/shard_*.npz 2>/dev/null | wc -l)
  echo "$(date +%T) labels: $shards shards"; pack
  [ "$shards" -gt 0 ] || { echo "no label shard: see $OUT/logs/labels.0"; exit 1; }
fi
if stage retest && [ ! -f "$OUT/reliability/reliability.json" ]; then
  # shellcheck disable=SC2086
  job "$OUT/logs/retest" timeout "$LABEL_SECONDS" python -m experiments.label_resolution --out "$OUT/labels_retest" \
    --reference-planner $PLANNER --time-budget "$BUDGET" --seed "$LABEL_SEED" --plan-seed "${RETEST_PLAN_SEED:-62000}" \
    --workers "$workers" $LABEL_FLAGS --scenes "${RETEST_SCENES:-512}"
  python -m experiments.tradeoff --reliability "$OUT/labels" "$OUT/labels_retest" --out "$OUT/reliability" \
    > "$OUT/logs/reliability" 2>&1
  echo "$(date +%T) retest: $(tail -1 "$OUT/logs/reliability")"; pack
  [ -f "$OUT/reliability/reliability.json" ] || { echo "the retest failed: see $OUT/logs/retest.0"; exit 1; }
fi
if stage regressor && [ ! -f "$OUT/regressor/done" ]; then
  # shellcheck disable=SC2086
  python -m experiments.train_regressor --labels "$OUT/labels" --out "$OUT/regressor" ${REGRESSOR_FLAGS:-} \
    > "$OUT/logs/regressor" 2>&1 && touch "$OUT/regressor/done"
  echo "$(date +%T) regressor: $(tail -1 "$OUT/logs/regressor")"; pack
  [ -f "$OUT/regressor/done" ] || { echo "the regressor failed: see $OUT/logs/regressor"; exit 1; }
fi
if stage evaluate; then
  regressor=$OUT/regressor/ckpt
  OUT="$OUT/eval" BUDGETS="$BUDGET" EPISODES="${EPISODES:-256}" SEED="${SEED:-52000}" \
    TASKS="${TASKS:-gather redistribute}" METHODS="${METHODS:-adaptive oracle best5 25 50}" \
    FLAGS="$PLANNER --regressor $regressor ${EVAL_FLAGS:-}" GPUS=$gpus PER_GPU=$PER_GPU \
    bash "$(dirname "$0")/gpu_fig5_reference.sh"
  pack
fi
echo "$(date +%T) done"; touch "$OUT/done"
