#!/usr/bin/env bash
# Issue 65 on one host of several GPUs: data for the judge, its training throughput on 1, 2 and all GPUs, the judge
# trained (--recipe judge, data-parallel over every GPU of the host), and its one- and five-step errors beside the
# shipped model's.
#   WORK=/tmp/judge bash scripts/gpu_judge.sh     # a 4-GPU host, 64 cores
# Data (C MuJoCo on the host cores): R1..R3 random pushes (seeds 31-33) and P, half the pushes the shipped model's
# planner chooses (seed 35), EPISODES episodes each. Throughput: SPEED_STEPS steps of the recipe on 1, 2 and all GPUs
# (metrics.jsonl's samples_per_s). The judge: STEPS steps (the recipe's 16,000 = 10.2 M push samples), BOX minutes at
# most. $WORK/results.tar.gz (logs, metrics, checkpoints; no data) is rewritten after every stage; a stage whose
# output exists is skipped, so a rerun on a warm machine goes on.
# Env: WORK, EPISODES (1536), STEPS (16000), BOX (minutes, 40), SPEED_STEPS (300), WORKERS (host cores a data job),
# WINDOWS (512, eval_dynamics's). A CPU dry run: EPISODES=10 STEPS=20 SPEED_STEPS=4 WINDOWS=8 GPUS=1
# DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0 --image-size 64" WORKERS=2.
set -uo pipefail
WORK=${WORK:-/tmp/judge}; EPISODES=${EPISODES:-1536}; STEPS=${STEPS:-16000}; BOX=${BOX:-40}
SPEED_STEPS=${SPEED_STEPS:-300}; WINDOWS=${WINDOWS:-512}; WORKERS=${WORKERS:-$(nproc)}
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || echo 1)}
SHIPPED=dynres_jax/checkpoints/dynamics
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"

log "start: $EPISODES episodes a set, $STEPS judge steps on $gpus GPUs, $WORKERS cores"
for i in 1 2 3; do gen "R$i" "3$i" 128 "$WORKERS"; done
gen P 35 64 "$WORKERS" --planned 0.5
pack
data=("$WORK/data/R1" "$WORK/data/R2" "$WORK/data/R3" "$WORK/data/P")

for n in 1 2 "$gpus"; do  # throughput: the same recipe on n GPUs
  [ "$n" -le "$gpus" ] && [ ! -f "$WORK/runs/speed$n/metrics.jsonl" ] || continue
  CUDA_VISIBLE_DEVICES=$(seq -s, 0 $((n - 1))) python -m experiments.train_dynamics --recipe judge \
    --data "${data[@]}" --out "$WORK/runs/speed$n" --steps "$SPEED_STEPS" --eval-every "$SPEED_STEPS" --quiet \
    > "$WORK/logs/speed$n.log" 2>&1
  log "speed on $n GPUs: $(tail -1 "$WORK/runs/speed$n/metrics.jsonl")"
done
pack

if [ ! -f "$WORK/runs/judge/done" ]; then
  log "train the judge"
  python -m experiments.train_dynamics --recipe judge --data "${data[@]}" --out "$WORK/runs/judge" --steps "$STEPS" \
    --max-minutes "$BOX" --quiet > "$WORK/logs/train_judge.log" 2>&1 && touch "$WORK/runs/judge/done"
  log "judge: $(tail -1 "$WORK/runs/judge/metrics.jsonl")"
fi
pack

for m in "$SHIPPED" "$WORK/runs/judge/ckpt"; do
  name=$([ "$m" = "$SHIPPED" ] && echo shipped || echo judge)
  [ -f "$WORK/runs/eval/$name/summary.json" ] && continue
  python -m experiments.eval_dynamics --ckpt "$m" --data "$WORK/data/R1" --out "$WORK/runs/eval/$name" \
    --windows "$WINDOWS" > "$WORK/logs/eval_$name.log" 2>&1
  log "eval $name: $(tail -3 "$WORK/logs/eval_$name.log" | head -1)"
done
pack
touch "$WORK/done"
log "done"
