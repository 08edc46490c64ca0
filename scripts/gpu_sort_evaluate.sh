#!/usr/bin/env bash
# Sort's headline through evaluate (issue 66 item 1): `evaluate --task sort` on each kind pair (coffee + candy,
# almond + M&M, rice + granola; each kind at half its default count, evaluate's default for Sort), EPISODES paired
# episodes from seed SEED, methods METHODS, STEPS MPC steps, 50 samples x 100 Adam steps, no time budget, Sort's
# shipped model. Each pair is one jax.distributed job over every GPU of the host (scripts/gpu_job.sh: PER_GPU
# processes a GPU, episodes split by process); results in $OUT/sort_evaluate/sort-A-B/ (METHOD.json with each
# episode's kind shares, mixing and success; summary.json with Wilson intervals, paired bootstrap and McNemar; the
# processes' logs beside it), packed as $OUT/sort_evaluate.tar.gz. A rerun resumes (finished methods are kept).
#   OUT=runs/sort_eval bash scripts/gpu_sort_evaluate.sh
# Env: EPISODES (256), SEED (60000: seeds the project had not used), METHODS ("50"; e.g. "50 rerank best5"), STEPS (30),
#      PAIRS ("coffee-candy almond-mnm rice-granola"), FLAGS (more evaluate flags, e.g. --arrived 0.9 for the old
#      arrival rule), PER_GPU (2), GPUS (a CPU dry run: GPUS=1 EPISODES=2 STEPS=1 FLAGS="--quick --samples 4 ...").
set -uo pipefail
OUT=${OUT:-runs/sort_eval}; EPISODES=${EPISODES:-256}; SEED=${SEED:-60000}; METHODS=${METHODS:-50}
STEPS=${STEPS:-30}; PAIRS=${PAIRS:-"coffee-candy almond-mnm rice-granola"}
. "$(dirname "$0")/gpu_job.sh"
RUNS=$OUT/sort_evaluate; mkdir -p "$RUNS"
for pair in $PAIRS; do
  a=${pair%-*}; b=${pair#*-}
  # shellcheck disable=SC2086
  job "$RUNS/sort-$pair.log" python -m experiments.evaluate --task sort --kind "$a" "$b" --episodes "$EPISODES" \
    --seed "$SEED" --mpc-steps "$STEPS" --samples 50 --adam-steps 100 --methods $METHODS --workers "$workers" \
    ${FLAGS:-} --out "$RUNS/sort-$pair"
  tail -n 6 "$RUNS/sort-$pair.log.0"
done
tar -czf "$OUT/sort_evaluate.tar.gz" -C "$OUT" sort_evaluate
