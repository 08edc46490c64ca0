#!/usr/bin/env bash
# Fig. 5 in the authors' setting (issue 51 item 3; docs/reference_planner): their planner (--reference-planner: fixed
# starting pushes over the workspace, no warm start, their Adam step, no ω buckets, their fitted step prices) under
# their loop budget, on every GPU of one host as one jax.distributed job of PER_GPU processes a GPU (one simulates in
# C MuJoCo while another plans), each with its share of the host's cores:
#   OUT=/root/fig5ref bash scripts/gpu_fig5_reference.sh
# For each budget of BUDGETS and task of TASKS: EPISODES paired episodes from seed SEED, methods METHODS (the oracle
# over ω and its control, best-of-5 at ω = 50, first: their difference is the ω part of the oracle's gain). A stage
# whose summary exists is skipped; a killed stage resumes per method. $OUT/results.tar.gz after every stage.
# Env: OUT, EPISODES (256), SEED (50000), BUDGETS ("2"), TASKS ("gather redistribute"), METHODS ("oracle best5 50 25
# 100 75"), PER_GPU (2), FLAGS (more evaluate flags, e.g. "--resamples 1"; a CPU dry run: GPUS=1 PER_GPU=1
# EPISODES=2 FLAGS="--quick --mpc-steps 1").
set -uo pipefail
OUT=${OUT:-/root/fig5ref}; EPISODES=${EPISODES:-256}; SEED=${SEED:-50000}; BUDGETS=${BUDGETS:-2}
TASKS=${TASKS:-"gather redistribute"}; METHODS=${METHODS:-"oracle best5 50 25 100 75"}
# shellcheck source=scripts/gpu_job.sh
. "$(dirname "$0")/gpu_job.sh"
mkdir -p "$OUT"
pack() { tar -czf "$OUT/results.tmp" -C "$OUT" --exclude results.tar.gz --exclude results.tmp . 2>/dev/null
         mv "$OUT/results.tmp" "$OUT/results.tar.gz"; }
for budget in $BUDGETS; do
  for task in $TASKS; do
    name=${task}_${budget}s
    [ -f "$OUT/$name/summary.json" ] && continue
    echo "$(date +%T) $name: $n processes on $gpus GPUs, $workers workers each"
    # shellcheck disable=SC2086
    job "$OUT/$name.log" python -m experiments.evaluate --task "$task" --episodes "$EPISODES" --samples 50 \
      --adam-steps 200 --time-budget "$budget" --reference-planner --seed "$SEED" --methods $METHODS \
      --workers "$workers" --out "$OUT/$name" ${FLAGS:-}
    echo "$(date +%T) $name: $(grep -c 'final d' "$OUT/$name.log.0") methods"; pack
  done
done
echo "$(date +%T) done"; touch "$OUT/done"
