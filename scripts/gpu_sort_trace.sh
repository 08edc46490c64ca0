#!/usr/bin/env bash
# Issue 48 item 6 on one GPU machine (docs/sort): Sort's closed loop with this tree against a reference tree REF (an
# older checkout, e.g. `git archive COMMIT dynres_jax experiments | tar -x -C REF`), on the same seeds, pairs and model
# (Sort's shipped one), through scripts/gpu_ladder.sh: this tree's episodes land in sort-PAIR-model/, the reference's
# in sort-PAIR-model-ref/. With FLOOR=1, studies.noise_floor's achievable floor runs beside them on a few cores.
#   REF=.old OUT=runs/sort_trace N=16 SEED=6000 FLOOR=1 bash scripts/gpu_sort_trace.sh
#   python scripts/ladder_table.py --runs runs/sort_trace/unpacked --out docs/sort/tuning
# Env: REF (required), OUT (runs/sort_trace), N (episodes per pair, 16), SEED (6000: tuning seeds), FLOOR (0).
set -uo pipefail
REF=$(cd "${REF:?REF names the reference tree}" && pwd); OUT=$(mkdir -p "${OUT:-runs/sort_trace}" && cd "$OUT" && pwd)
N=${N:-16}; SEED=${SEED:-6000}; here=$(pwd)
mkdir -p /tmp/ref && rm -rf /tmp/ref/ckpt && cp -r dynres_jax/checkpoints/sort_dynamics /tmp/ref/ckpt
: > /tmp/sort_new.jobs; : > /tmp/sort_ref.jobs
for i in 0 1 2; do
  pair=$(echo coffee-candy almond-mnm rice-granola | cut -d' ' -f$((i + 1)))
  echo "$i sort $pair model $N" >> /tmp/sort_new.jobs
  echo "$((i + 3)) sort $pair model $N /tmp/ref/ckpt" >> /tmp/sort_ref.jobs
done
if [ "${FLOOR:-0}" = 1 ]; then
  (python -m studies.noise_floor --out "$OUT/floor" --ckpt dynres_jax/checkpoints/dynamics \
     dynres_jax/checkpoints/sort_dynamics --scenes 32 --worlds 8 --pushes 2 --twins 5 --sigmas 1 3 --omegas 50 \
     --workers 4 --seed 1 --no-progress > "$OUT/floor.log" 2>&1; echo "floor done" >> "$OUT/stages.log") &
fi
(CORES=12 SEED=$SEED OUT="$OUT/new" WORK=/tmp/sort_new JOBS=/tmp/sort_new.jobs bash scripts/gpu_ladder.sh \
  >> "$OUT/stages.log" 2>&1) &
(cd "$REF" && CORES=12 SEED=$SEED OUT="$OUT/ref" WORK=/tmp/sort_ref JOBS=/tmp/sort_ref.jobs bash "$here/scripts/gpu_ladder.sh" \
  >> "$OUT/stages.log" 2>&1) &
wait
echo "all done" >> "$OUT/stages.log"
