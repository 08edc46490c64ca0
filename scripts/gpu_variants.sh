#!/usr/bin/env bash
# Policy variants side by side through evaluate (issue 66): `evaluate --task TASK` on each of KINDS (Sort: pairs A-B,
# default coffee + candy, almond + M&M, rice + granola, each kind at half its default count, evaluate's default for
# Sort; else one kind each, default coffee), EPISODES paired episodes from seed SEED, methods METHODS, STEPS MPC steps,
# 50 samples x 100 Adam steps, no time budget, the task's shipped model, once per policy variant (VARIANTS). Every
# (kind, variant) run is one process, all at once, spread over the host's GPUs (Sort's per-episode perception and A*
# run on the host, so runs side by side share the GPUs well); results in $OUT/variants/VARIANT/TASK-KIND/ (METHOD.json
# with each episode's results and success; summary.json with Wilson intervals, paired bootstrap and McNemar between
# its methods; the log beside it), packed as $OUT/variants.tar.gz. Variants pair episode by episode (episode i's
# scene, goals and keys come from (SEED, i)): scripts/variants.py compares them. A rerun resumes (finished methods
# are kept).
#   OUT=runs/sort_eval bash scripts/gpu_variants.sh
#   OUT=runs/redis TASK=redistribute FLAGS="--letters F2O7" VARIANTS="base=;steps40=--mpc-steps 40" bash scripts/gpu_variants.sh
# Env: TASK (sort), KINDS (see above), EPISODES (64), SEED (60000: seeds the project had not used), METHODS ("50";
#      e.g. "50 rerank"), STEPS (30; a variant's --mpc-steps wins), VARIANTS ("base=": NAME=FLAGS separated by ';',
#      e.g. "base=;mix3=--mixing 3;old=--arrived 0.9"), FLAGS (more evaluate flags for every run), GPUS (a CPU dry
#      run: GPUS=1 EPISODES=2 STEPS=1 FLAGS="--quick"), SPLIT (1: each run split over this many processes of one
#      job, `evaluate --coordinator`, the processes of all runs dealt over the GPUs in turn; e.g. SPLIT=4 on a 4-GPU host for 256-episode
#      headlines: `TASK=sort EPISODES=256 SPLIT=4 bash scripts/gpu_variants.sh`), FIRST_GPU (0: with GPUS, the block of
#      GPUs FIRST_GPU .. FIRST_GPU + GPUS - 1, so that several invocations share a host side by side).
set -uo pipefail
OUT=${OUT:-runs/sort_eval}; EPISODES=${EPISODES:-64}; SEED=${SEED:-60000}; METHODS=${METHODS:-50}
STEPS=${STEPS:-30}; TASK=${TASK:-sort}; VARIANTS=${VARIANTS:-"base="}
if [ "$TASK" = sort ]; then KINDS=${KINDS:-"coffee-candy almond-mnm rice-granola"}; else KINDS=${KINDS:-coffee}; fi
gpus=${GPUS:-$(n=$(nvidia-smi -L 2>/dev/null | grep -c "^GPU"); echo $(( n > 0 ? n : 1 )))}
IFS=';' read -ra variants <<< "$VARIANTS"
SPLIT=${SPLIT:-1}
[ "$SPLIT" -le "$gpus" ] || { echo "SPLIT=$SPLIT: a job's processes need a GPU each (NCCL refuses two on one GPU); this host has $gpus" >&2; exit 2; }
runs=$(( ${#variants[@]} * $(wc -w <<< "$KINDS") * SPLIT )); workers=$(( $(nproc) / runs )); [ "$workers" -ge 1 ] || workers=1
fraction=$(python -c "print(round(0.9 / -(-$runs // $gpus), 2))")  # GPU memory a run: the runs on one GPU share 90 %
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}
RUNS=$OUT/variants; i=0; p=0; pids=()  # i: runs, p: processes (process p on GPU p mod GPUS)
for variant in "${variants[@]}"; do
  name=${variant%%=*}; flags=${variant#*=}
  for kind in $KINDS; do
    mkdir -p "$RUNS/$name"
    for j in $(seq 0 $((SPLIT - 1))); do
      [ "$j" -eq 0 ] && port=$(python -c "import socket; s = socket.socket(); s.bind(('', 0)); print(s.getsockname()[1])")
      job=(); [ "$SPLIT" -gt 1 ] && job=(--coordinator "localhost:$port" --num-processes "$SPLIT" --process-id "$j")
      log="$RUNS/$name/$TASK-$kind.log"; [ "$j" -gt 0 ] && log="$RUNS/$name/$TASK-$kind.$j.log"
      # shellcheck disable=SC2086
      CUDA_VISIBLE_DEVICES=$((${FIRST_GPU:-0} + p % gpus)) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction python -m experiments.evaluate \
        --task "$TASK" --kind ${kind/-/ } --episodes "$EPISODES" --seed "$SEED" --mpc-steps "$STEPS" --samples 50 \
        --adam-steps 100 --methods $METHODS --workers "$workers" $flags ${FLAGS:-} --out "$RUNS/$name/$TASK-$kind" \
        ${job[@]+"${job[@]}"} > "$log" 2>&1 &
      pids+=($!); p=$((p + 1))
    done
    i=$((i + 1))
  done
done
for p in "${pids[@]}"; do wait "$p"; done
for log in "$RUNS"/*/"$TASK"-*[!0-9].log; do echo "== $log"; grep -E "^ *[a-z0-9]+( - [a-z0-9]+)?: " "$log" | tail -n 4; done
tar -czf "$OUT/variants.tar.gz" -C "$OUT" variants
