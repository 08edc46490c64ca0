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
TASKS=${TASKS:-"gather redistribute"}; METHODS=${METHODS:-"oracle best5 50 25 100 75"}; PER_GPU=${PER_GPU:-2}
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || true)}
n=$((gpus * PER_GPU)); workers=$(( $(nproc) / n )); [ "$workers" -ge 1 ] || workers=1
fraction=$(python -c "print(round(0.9 / $PER_GPU, 2))")
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}  # the second stage reuses compiles
mkdir -p "$OUT"
pack() { tar -czf "$OUT/results.tmp" -C "$OUT" --exclude results.tar.gz --exclude results.tmp . 2>/dev/null
         mv "$OUT/results.tmp" "$OUT/results.tar.gz"; }
for budget in $BUDGETS; do
  for task in $TASKS; do
    name=${task}_${budget}s
    [ -f "$OUT/$name/summary.json" ] && continue
    echo "$(date +%T) $name: $n processes on $gpus GPUs, $workers workers each"
    port=$((20000 + RANDOM % 20000)); pids=()
    for ((i = 0; i < n; i++)); do
      # shellcheck disable=SC2086
      CUDA_VISIBLE_DEVICES=$((i % gpus)) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction python -m experiments.evaluate \
        --task "$task" --episodes "$EPISODES" --samples 50 --adam-steps 200 --time-budget "$budget" \
        --reference-planner --seed "$SEED" --methods $METHODS --workers "$workers" --out "$OUT/$name" \
        --coordinator "localhost:$port" --num-processes "$n" --process-id "$i" ${FLAGS:-} > "$OUT/$name.log.$i" 2>&1 &
      pids+=($!)
    done
    for p in "${pids[@]}"; do wait "$p"; done
    echo "$(date +%T) $name: $(grep -c 'final d' "$OUT/$name.log.0") methods"; pack
  done
done
echo "$(date +%T) done"; touch "$OUT/done"
