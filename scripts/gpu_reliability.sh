#!/usr/bin/env bash
# Label reliability and paper Fig. 4 on every GPU of one host (results in $OUT): the same scenes labelled twice with
# independent plan seeds under the time budget (every ω of a scene planned from the same REPEATS keys: common random
# numbers), each labelling a jax.distributed job of PER_GPU processes a GPU (scripts/gpu_job.sh), then their
# agreement (experiments.tradeoff --reliability) and Fig. 4 on the first labelling.
#   OUT=runs/rel bash scripts/gpu_reliability.sh                       # 512 scenes: 256 letter, 128 near-goal pairs
#   OUT=runs/fig4 SCENES=2048 SEED=64000 bash scripts/gpu_reliability.sh   # issue 51 item 5: 512 pairs a claim
# Env: SCENES (512), REPEATS (4), SEED (21: the scenes), LABEL_SECONDS (per labelling, 900), BUDGET (0.25 s per
# decision), TIMING (docs/budget/timing_cpu.json), SAMPLES (50), BATCH (128), PER_GPU (2), FLAGS (more
# label_resolution flags). A labelling cut by LABEL_SECONDS resumes on a rerun. A CPU dry run: GPUS=1 PER_GPU=1
# SCENES=8 BATCH=4 REPEATS=1 FLAGS="--evals 6 --pieces 60 --adam-steps 4" (50 samples: the timing table's).
set -uo pipefail
OUT=${OUT:-runs/rel}; SCENES=${SCENES:-512}; REPEATS=${REPEATS:-4}; SEED=${SEED:-21}
LABEL_SECONDS=${LABEL_SECONDS:-900}; BUDGET=${BUDGET:-0.25}; TIMING=${TIMING:-docs/budget/timing_cpu.json}
SAMPLES=${SAMPLES:-50}; BATCH=${BATCH:-128}
# shellcheck source=scripts/gpu_job.sh
. "$(dirname "$0")/gpu_job.sh"
mkdir -p "$OUT"
for plan_seed in 1 2; do
  # shellcheck disable=SC2086
  job "$OUT/labels_$plan_seed.log" timeout "$LABEL_SECONDS" python -m experiments.label_resolution \
    --out "$OUT/labels_$plan_seed" --scenes "$SCENES" --batch "$BATCH" --samples "$SAMPLES" --repeats "$REPEATS" \
    --time-budget "$BUDGET" --timing "$TIMING" --seed "$SEED" --plan-seed "$plan_seed" --workers "$workers" ${FLAGS:-}
  echo "$(date +%T) labels $plan_seed: $(ls "$OUT/labels_$plan_seed"/shard_*.npz 2>/dev/null | wc -l) shards"
done
python -m experiments.tradeoff --reliability "$OUT/labels_1" "$OUT/labels_2" --out "$OUT/reliability" > "$OUT/reliability.log" 2>&1
python -m experiments.tradeoff --labels "$OUT/labels_1" --out "$OUT/fig4" > "$OUT/fig4.log" 2>&1
tail -3 "$OUT/reliability.log"; tail -3 "$OUT/fig4.log"
