#!/usr/bin/env bash
# Sort per kind pair (issue 26's table): coffee + candy, almond + M&M, rice + granola, each kind at half its default
# count (config.DEFAULT_PIECES: two piles of one pile's area), SEEDS episodes each, the three pairs side by side on one
# GPU. Every episode's metrics.json lands in $OUT/sort/PAIR/SEED/; the packed folder is $OUT/sort.tar.gz.
#   OUT=runs/sort bash scripts/gpu_sort.sh            # Env: SEEDS ("0 1 2 3 4 5"), STEPS (30), FLAGS (more sort flags),
#                                                     #      LANES (1: processes per pair, each taking every LANES-th seed)
set -uo pipefail
OUT=${OUT:-runs/sort}; SEEDS=${SEEDS:-"0 1 2 3 4 5"}; STEPS=${STEPS:-30}; LANES=${LANES:-1}
mkdir -p "$OUT/sort"
XLA_PYTHON_CLIENT_MEM_FRACTION=$(python -c "print(round(0.9 / (3 * $LANES), 3))"); export XLA_PYTHON_CLIENT_MEM_FRACTION
pair() {  # KIND_A KIND_B LANE
  local a=$1 b=$2 lane=$3 na nb i=0
  na=$(python -c "from dynres_jax.config import DEFAULT_PIECES as P; print(P['$a'] // 2)")
  nb=$(python -c "from dynres_jax.config import DEFAULT_PIECES as P; print(P['$b'] // 2)")
  for s in $SEEDS; do
    i=$((i + 1)); [ $(((i - 1) % LANES)) -eq "$lane" ] || continue
    # shellcheck disable=SC2086
    python -m experiments.sort --kind "$a" "$b" --pieces "$na" "$nb" --seed "$s" --mpc-steps "$STEPS" ${FLAGS:-} \
      --out "/tmp/sort/$a-$b/$s" > "/tmp/sort/$a-$b.$s.log" 2>&1 || echo "$a-$b seed $s failed"
    mkdir -p "$OUT/sort/$a-$b/$s"
    cp "/tmp/sort/$a-$b/$s/metrics.json" "/tmp/sort/$a-$b.$s.log" "$OUT/sort/$a-$b/$s/" 2>/dev/null
    tail -1 "/tmp/sort/$a-$b.$s.log"
  done
}
mkdir -p /tmp/sort
for lane in $(seq 0 $((LANES - 1))); do
  pair coffee candy "$lane" & pair almond mnm "$lane" & pair rice granola "$lane" &
done
wait
tar -czf "$OUT/sort.tar.gz" -C "$OUT" sort && rm -rf "$OUT/sort"
