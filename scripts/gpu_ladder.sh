#!/usr/bin/env bash
# Issue 35's ladder on one GPU machine (docs/reach): the jobs of JOBS (a file) on its lanes at once, every lane on GPU
# (lane modulo the GPUs) with the host's cores and its GPUs' memory shared out. A job line is "LANE TASK KIND METHOD
# COUNT [CKPT]" (CKPT: a dynamics checkpoint folder, RUN/ckpt, planned with instead of the shipped one; its folder name
# RUN is added to the job's folder):
#   0 gather mnm best5 64                 evaluate's method on episodes 0..63 into LANE/gather-mnm-64/ (methods of one
#   1 redistribute coffee sim 32          task, kind and count share a folder; Redistribute's letters are LETTERS)
#   1 sort coffee-candy sim 12            experiments.sort --method on seeds SEED..SEED+11, one process per episode,
#                                         each kind at half its default count, into LANE/sort-coffee-candy-sim/SEED/
# Episode i is the same pile, goal and planner keys in every run (evaluate.episode_keys), so a method run on fewer
# episodes is paired with the others on its first ones. 50 samples x 100 Adam steps, ω = 50, no time budget. After
# each job a lane packs its folder into $OUT/laneN.tar.gz, so a call stopped by its time limit returns what finished;
# a job already done in WORK (a warm machine) is skipped.
#   OUT=runs/ladder JOBS=scripts/ladder/gather.jobs bash scripts/gpu_ladder.sh
# Env: JOBS, OUT, WORK (/tmp/ladder), CORES (the host's, shared out over the lanes), SEED (5000: seeds the project had
# not used), LETTERS (JTULY), STEPS (Sort's MPC steps, 30), FLAGS and SORT_FLAGS (more flags of evaluate and of sort:
# --ckpt DIR, ...).
set -uo pipefail
OUT=${OUT:-runs/ladder}; WORK=${WORK:-/tmp/ladder}; SEED=${SEED:-5000}; LETTERS=${LETTERS:-JTULY}; STEPS=${STEPS:-30}
JOBS=${JOBS:?JOBS names a file of job lines}
lanes=$(awk 'NF && $1 !~ /^#/ {print $1}' "$JOBS" | sort -u)
gpus=$(nvidia-smi -L 2>/dev/null | wc -l); gpus=$((gpus > 0 ? gpus : 1))
cores=${CORES:-$(nproc)}; share=$((cores / $(echo "$lanes" | wc -w))); share=$((share > 0 ? share : 1))
XLA_PYTHON_CLIENT_MEM_FRACTION=$(python -c "print(round(0.9 / -(-$(echo "$lanes" | wc -w) // $gpus), 3))")
export XLA_PYTHON_CLIENT_MEM_FRACTION
mkdir -p "$OUT" "$WORK"

half() { python -c "from dynres_jax.config import DEFAULT_PIECES as P; print(P['$1'] // 2)"; }

sort_job() {  # FOLDER PAIR METHOD SEEDS [MODEL FLAGS]: one process per episode, $share at once
  local folder=$1 a=${2%-*} b=${2#*-} method=$3 n=$4 flags=${5:-} na nb
  na=$(half "$a"); nb=$(half "$b")
  seq "$SEED" $((SEED + n - 1)) | XLA_PYTHON_CLIENT_PREALLOCATE=false xargs -P "$share" -I{} sh -c \
    "[ -f '$folder/{}/metrics.json' ] || python -m experiments.sort --kind $a $b --pieces $na $nb --seed {} \
     --mpc-steps $STEPS --method $method $flags ${SORT_FLAGS:-} --out '$folder/{}' > '$folder.{}.log' 2>&1 \
     || echo 'sort $a-$b $method seed {} failed'; rm -f '$folder/{}/episode.gif'"
}

lane() {  # LANE: its jobs in order
  local n=$1 task kind method count ckpt folder model
  export CUDA_VISIBLE_DEVICES=$((n % gpus))
  awk -v n="$n" 'NF && $1 !~ /^#/ && $1 == n {print $2, $3, $4, $5, $6}' "$JOBS" |
  while read -r task kind method count ckpt; do
    local t0=$SECONDS suffix="" model=()
    if [ -n "$ckpt" ]; then suffix="-$(basename "$(dirname "$ckpt")")"; model=(--ckpt "$ckpt"); fi
    if [ "$task" = sort ]; then
      folder="$WORK/lane$n/sort-$kind-$method$suffix"; mkdir -p "$folder"
      sort_job "$folder" "$kind" "$method" "$count" "${model[*]}"
    else
      folder="$WORK/lane$n/$task-$kind-$count$suffix"
      # shellcheck disable=SC2086
      python -m experiments.evaluate --task "$task" --kind "$kind" --episodes "$count" --methods "$method" \
        --samples 50 --adam-steps 100 --seed "$SEED" --letters "$LETTERS" --workers "$share" ${FLAGS:-} \
        "${model[@]}" --out "$folder" 2>&1 | grep -v "it/s\]" | tail -3
      rm -rf "$folder/parts"
    fi
    echo "lane $n: $task $kind $method $count $ckpt done in $((SECONDS - t0)) s"
    tar -czf "$OUT/lane$n.tmp" -C "$WORK" "lane$n" && mv "$OUT/lane$n.tmp" "$OUT/lane$n.tar.gz"
  done
}

for n in $lanes; do lane "$n" & done
wait
