#!/usr/bin/env bash
# Sort per kind pair (issue 26's table): coffee + candy, almond + M&M, rice + granola, each kind at half its default
# count (config.DEFAULT_PIECES: two piles of one pile's area), SEEDS episodes each, the three pairs side by side on one
# GPU. Every episode's metrics.json lands in $OUT/sort/PAIR/SEED/; the packed folder is $OUT/sort.tar.gz.
#   OUT=runs/sort bash scripts/gpu_sort.sh            # Env: SEEDS ("0 1 2 3 4 5"), STEPS (30), FLAGS (more sort flags)
set -uo pipefail
OUT=${OUT:-runs/sort}; SEEDS=${SEEDS:-"0 1 2 3 4 5"}; STEPS=${STEPS:-30}
mkdir -p "$OUT/sort"
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
pair() {  # KIND_A KIND_B
  local a=$1 b=$2 na nb
  na=$(python -c "from dynres_jax.config import DEFAULT_PIECES as P; print(P['$a'] // 2)")
  nb=$(python -c "from dynres_jax.config import DEFAULT_PIECES as P; print(P['$b'] // 2)")
  for s in $SEEDS; do
    # shellcheck disable=SC2086
    python -m experiments.sort --kinds "$a" "$b" --pieces "$na" "$nb" --seed "$s" --steps "$STEPS" ${FLAGS:-} \
      --out "/tmp/sort/$a-$b/$s" > "/tmp/sort/$a-$b.$s.log" 2>&1 || echo "$a-$b seed $s failed"
    mkdir -p "$OUT/sort/$a-$b/$s"
    cp "/tmp/sort/$a-$b/$s/metrics.json" "/tmp/sort/$a-$b.$s.log" "$OUT/sort/$a-$b/$s/" 2>/dev/null
    tail -1 "/tmp/sort/$a-$b.$s.log"
  done
}
mkdir -p /tmp/sort
pair coffee candy & pair almond mnm & pair rice granola & wait
tar -czf "$OUT/sort.tar.gz" -C "$OUT" sort && rm -rf "$OUT/sort"
