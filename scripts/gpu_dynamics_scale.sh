#!/usr/bin/env bash
# Issue 48 on one machine of G GPUs (G = 4 intended), every stage logged to $WORK/logs/stages.log:
# 1. Data: R (random, seed 21, EPISODES_R episodes) on half the host cores, and G on-policy sets P0..P(G-1) (seeds
#    30+g, EPISODES_P each, half the pushes the shipped model's plans), one per GPU; beside them the ranking set of
#    Redistribute (studies.ranking build: letters JTULY, seed 7800).
# 2. Throughput, each alone on its own GPU: the trainer of main before this issue ($OLD, a tree of c55a739: host-side
#    batches) and today's, at the shipped recipe's batch 64 and at each variant's batch; then variant A's batch over
#    2 and G GPUs (data-parallel).
# 3. The capacity study: VARIANTS trained side by side (variant i on GPU i), each MINUTES long at the speed its probe
#    measured (the cosine schedule's length set from it), on R and every P.
# 4. Scores: the ranking benchmark (studies.ranking score on $RANKING), the one-step error on the noise floor's windows
#    (studies.noise_floor), and the closed loop on tuning seeds (scripts/gpu_ladder.sh; Gather M&M and Redistribute
#    JTULY, COUNT episodes each, seeds from 6000) for the shipped model and each variant.
# Results: $WORK/results/ (logs, probe and run metrics, ranking and floor tables, lanes); $WORK/done at the end.
#   setsid nohup bash scripts/gpu_dynamics_scale.sh > /tmp/scale.log 2>&1 &
# On the lent machines: carry the wheels, $OLD and $RANKING on every call that runs or polls it (a carried folder is
# removed from the machine by a call that does not carry it: 2026-11-26's old-trainer probe and ranking stage failed
# so), and call python3 through a wrapper script, not a symbolic link (a link to a venv's python leaves the venv).
# Env: WORK (/tmp/s48), OLD (.old), RANKING (.rk: ranking sets), EPISODES_R (2048), EPISODES_P (256 a GPU),
# MINUTES (6), COUNT (64), VARIANTS ("NAME BATCH LR FLAGS;..."). A CPU dry run: EPISODES_R=10 EPISODES_P=10 MINUTES=0.3
# COUNT=1 DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0 --image-size 64" PROBE=4 RANKING=/tmp/rk_test
# RANKING_EPISODES=1 RANKING_FLAGS="--samples 4 --adam-steps 2" FLOOR="--scenes 1 --worlds 2 --pushes 1"
# FLAGS="--quick --samples 4 --adam-steps 2 --mpc-steps 1" (FLAGS: more evaluate flags, for gpu_ladder.sh).
set -uo pipefail
WORK=${WORK:-/tmp/s48}; OLD=$(realpath "${OLD:-.old}"); RANKING=${RANKING:-.rk}
EPISODES_R=${EPISODES_R:-2048}; EPISODES_P=${EPISODES_P:-256}; MINUTES=${MINUTES:-6}; COUNT=${COUNT:-64}
PROBE=${PROBE:-100}
VARIANTS=${VARIANTS:-"A 1024 2e-3 ;B 1024 2e-3 --hidden 128 --propagation-steps 5;C 512 1e-3 --processor gns --propagation-steps 3;D 256 1e-3 --processor gns --hidden 128 --propagation-steps 5"}
gpus=$(nvidia-smi -L 2>/dev/null | wc -l); gpus=$((gpus > 0 ? gpus : 1)); cores=$(nproc)
R=$WORK/results; mkdir -p "$R/logs" "$WORK/data" "$WORK/runs"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # data, probes and lanes share GPUs
log() { echo "$(date +%T) $*" | tee -a "$R/logs/stages.log"; }
data_dirs() { echo "$WORK/data/R"; for g in $(seq 0 $((gpus - 1))); do echo "$WORK/data/P$g"; done; }

gen() {  # NAME SEED WORLDS WORKERS EPISODES [FLAGS...]
  local name=$1 seed=$2 worlds=$3 workers=$4 episodes=$5; shift 5
  [ -f "$WORK/data/$name.done" ] && return  # made by an earlier call on this machine
  # shellcheck disable=SC2086
  python -m experiments.generate_data --out "$WORK/data/$name" --episodes "$episodes" --pushes 10 --worlds "$worlds" \
    --seed "$seed" --workers "$workers" --no-progress ${DATA_FLAGS:-} "$@" > "$R/logs/data_$name.log" 2>&1
  local status=$?
  [ $status -eq 0 ] && touch "$WORK/data/$name.done"
  log "data $name: $(grep -o '"frames": [0-9]*' "$R/logs/data_$name.log") (exit $status)"
}

train() {  # NAME GPUS BATCH LR STEPS [FLAGS...]: --recipe shipped on every data set
  local name=$1 devices=$2 batch=$3 lr=$4 steps=$5; shift 5
  local warmup=$((steps / 20))
  [ -f "$WORK/runs/$name.done" ] && return
  # shellcheck disable=SC2046
  CUDA_VISIBLE_DEVICES=$devices python -m experiments.train_dynamics --recipe shipped --data $(data_dirs) \
    --out "$WORK/runs/$name" --batch "$batch" --lr "$lr" --steps "$steps" --warmup "$warmup" \
    --eval-every "$(( steps > 4 ? steps / 4 : 1 ))" --ckpt-every "$steps" --quiet "$@" \
    > "$R/logs/train_$name.log" 2>&1 && touch "$WORK/runs/$name.done"
  log "train $name ($devices, batch $batch, $steps steps): $(tail -1 "$WORK/runs/$name/metrics.jsonl")"
}

speed() { python -c "import json,sys; print(json.loads(open(sys.argv[1]).readlines()[-1])['samples_per_s'] or 0)" \
  "$WORK/runs/$1/metrics.jsonl" 2>/dev/null || echo 0; }

log "start: $gpus GPUs, $cores cores"
# 1. data
gen R 21 128 $((cores / 2)) "$EPISODES_R" &
for g in $(seq 0 $((gpus - 1))); do
  CUDA_VISIBLE_DEVICES=$g gen "P$g" $((30 + g)) 64 $((cores / 2 / gpus)) "$EPISODES_P" --planned 0.5 --policy shipped &
done
[ -f "$R/rk_redistribute/ranking_set.npz" ] || CUDA_VISIBLE_DEVICES=0 python -m studies.ranking build --out "$R/rk_redistribute" --task redistribute --kind coffee \
  --letters JTULY --episodes "${RANKING_EPISODES:-12}" --capture 0 4 8 12 --seed 7800 --workers 8 ${RANKING_FLAGS:-} \
  > "$R/logs/ranking_build.log" 2>&1 && log "ranking set: $(tail -1 "$R/logs/ranking_build.log")"
wait

# 2. throughput probes, one per GPU at once: the old trainer and today's at batch 64, then each variant's batch
# shellcheck disable=SC2046
(cd "$OLD" && CUDA_VISIBLE_DEVICES=0 python -m experiments.train_dynamics --recipe shipped --data $(data_dirs) \
  --out "$WORK/runs/probe_old" --steps "$PROBE" --eval-every "$PROBE" --val-batches 1 --quiet \
  > "$R/logs/train_probe_old.log" 2>&1; log "probe old trainer, batch 64: $(speed probe_old) samples/s") &
train probe_new64 1 64 1e-3 "$PROBE" --val-batches 1 &
wait
i=0
IFS=';' read -ra specs <<< "$VARIANTS"
for spec in "${specs[@]}"; do
  read -r name batch lr flags <<< "$spec"
  # shellcheck disable=SC2086
  train "probe_$name" $((i % gpus)) "$batch" "$lr" "$PROBE" --val-batches 1 $flags &
  i=$((i + 1))
done
wait
read -r name batch lr flags <<< "${specs[0]}"
for n in 2 "$gpus"; do
  [ "$n" -le "$gpus" ] || continue
  # shellcheck disable=SC2086
  train "probe_${name}_x$n" "$(seq -s, 0 $((n - 1)))" $((batch * n)) "$lr" "$PROBE" --val-batches 1 $flags
done
for p in probe_old probe_new64 $(for s in "${specs[@]}"; do echo "probe_${s%% *}"; done) probe_${name}_x2 \
  "probe_${name}_x$gpus"; do echo "$p $(speed "$p")"; done > "$R/throughput.txt"
log "throughput: $(tr '\n' ';' < "$R/throughput.txt")"

# 3. the variants side by side, MINUTES each at its probed speed
i=0
for spec in "${specs[@]}"; do
  read -r name batch lr flags <<< "$spec"
  steps=$(python -c "print(max(20, int(0.9 * $MINUTES * 60 * $(speed "probe_$name") / $batch)))")
  # shellcheck disable=SC2086
  train "$name" $((i % gpus)) "$batch" "$lr" "$steps" $flags &
  i=$((i + 1))
done
wait
mkdir -p "$R/runs"
for spec in "${specs[@]}"; do
  n=${spec%% *}; cp "$WORK/runs/$n/metrics.jsonl" "$R/runs/$n.metrics.jsonl"
  tar -czf "$R/runs/$n.tar.gz" -C "$WORK/runs" "$n"
done
ckpts=$(for s in "${specs[@]}"; do echo "$WORK/runs/${s%% *}/ckpt"; done)

# 4. scores: ranking and the floor's windows beside the closed loop's lanes
# shellcheck disable=SC2086
CUDA_VISIBLE_DEVICES=0 python -m studies.ranking score --set "$RANKING"/* "$R/rk_redistribute" --ckpt shipped sweep $ckpts \
  --out "$R/ranking.md" > "$R/logs/ranking.log" 2>&1; log "ranking: $(cat "$R/ranking.md" | tr '\n' ' ' | head -c 300)"
# shellcheck disable=SC2086
(CUDA_VISIBLE_DEVICES=0 python -m studies.noise_floor --out "$WORK/floor" ${FLOOR:---scenes 32 --worlds 8 --pushes 2} --sigmas 1 \
  --ckpt dynres_jax/checkpoints/dynamics $ckpts --workers $((cores / 4)) --no-progress > "$R/logs/floor.log" 2>&1;
  cp "$WORK/floor/floor.md" "$WORK/floor/floor.json" "$R/" 2>/dev/null; log "floor done") &
jobs=$WORK/closed_loop.jobs; : > "$jobs"
lane=0
for c in "" $ckpts; do
  echo "$((lane % gpus)) gather mnm 50 $COUNT $c" >> "$jobs"; echo "$(((lane + 1) % gpus)) redistribute coffee 50 $COUNT $c" >> "$jobs"
  lane=$((lane + 2))
done
OUT=$R/lanes WORK=$WORK/ladder JOBS=$jobs SEED=6000 bash scripts/gpu_ladder.sh > "$R/logs/ladder.log" 2>&1
log "closed loop: $(grep -c done "$R/logs/ladder.log") jobs done"
wait
log "done"
touch "$WORK/done"
