#!/usr/bin/env bash
# Sort's headline through evaluate (issue 66 item 1): `evaluate --task sort` on each kind pair (coffee + candy,
# almond + M&M, rice + granola; each kind at half its default count, evaluate's default for Sort), EPISODES paired
# episodes from seed SEED, methods METHODS, STEPS MPC steps, 50 samples x 100 Adam steps, no time budget, Sort's
# shipped model, once per policy variant (VARIANTS). Every (pair, variant) run is one process, all at once, spread
# over the host's GPUs (Sort's per-episode perception and A* run on the host, so runs side by side share the GPUs
# well); results in $OUT/sort_evaluate/VARIANT/sort-A-B/ (METHOD.json with each episode's kind shares, mixing and
# success; summary.json with Wilson intervals, paired bootstrap and McNemar between its methods; the log beside it),
# packed as $OUT/sort_evaluate.tar.gz. Variants pair episode by episode (episode i's scene, goals and keys come from
# (SEED, i)): scripts/sort_variants.py compares them. A rerun resumes (finished methods are kept).
#   OUT=runs/sort_eval bash scripts/gpu_sort_evaluate.sh
# Env: EPISODES (64), SEED (60000: seeds the project had not used), METHODS ("50"; e.g. "50 rerank"), STEPS (30),
#      PAIRS ("coffee-candy almond-mnm rice-granola"), VARIANTS ("base=": NAME=FLAGS separated by ';', e.g.
#      "base=;mix3=--mixing 3;old=--arrived 0.9"), FLAGS (more evaluate flags for every run), GPUS (a CPU dry run:
#      GPUS=1 EPISODES=2 STEPS=1 FLAGS="--quick").
set -uo pipefail
OUT=${OUT:-runs/sort_eval}; EPISODES=${EPISODES:-64}; SEED=${SEED:-60000}; METHODS=${METHODS:-50}
STEPS=${STEPS:-30}; PAIRS=${PAIRS:-"coffee-candy almond-mnm rice-granola"}; VARIANTS=${VARIANTS:-"base="}
gpus=${GPUS:-$(n=$(nvidia-smi -L 2>/dev/null | grep -c "^GPU"); echo $(( n > 0 ? n : 1 )))}
IFS=';' read -ra variants <<< "$VARIANTS"
runs=$(( ${#variants[@]} * $(wc -w <<< "$PAIRS") )); workers=$(( $(nproc) / runs )); [ "$workers" -ge 1 ] || workers=1
fraction=$(python -c "print(round(0.9 / -(-$runs // $gpus), 2))")  # GPU memory a run: the runs on one GPU share 90 %
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}
RUNS=$OUT/sort_evaluate; i=0; pids=()
for variant in "${variants[@]}"; do
  name=${variant%%=*}; flags=${variant#*=}
  for pair in $PAIRS; do
    a=${pair%-*}; b=${pair#*-}; mkdir -p "$RUNS/$name"
    # shellcheck disable=SC2086
    CUDA_VISIBLE_DEVICES=$((i % gpus)) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction python -m experiments.evaluate \
      --task sort --kind "$a" "$b" --episodes "$EPISODES" --seed "$SEED" --mpc-steps "$STEPS" --samples 50 \
      --adam-steps 100 --methods $METHODS --workers "$workers" $flags ${FLAGS:-} --out "$RUNS/$name/sort-$pair" \
      > "$RUNS/$name/sort-$pair.log" 2>&1 &
    pids+=($!); i=$((i + 1))
  done
done
for p in "${pids[@]}"; do wait "$p"; done
for log in "$RUNS"/*/sort-*.log; do echo "== $log"; grep -E "^ *[a-z0-9]+( - [a-z0-9]+)?: " "$log" | tail -n 4; done
tar -czf "$OUT/sort_evaluate.tar.gz" -C "$OUT" sort_evaluate
