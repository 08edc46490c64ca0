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
# Closed loop: evaluate --methods 50 judge on M&M Gather, EVAL_EPISODES episodes from seed 7000 (tuning seeds: the
# headline is measured once, later, on fresh ones).
# Env: WORK, PLANNED (0: no set P), EPISODES (1536), STEPS (16000), BOX (minutes, 40), SPEED_STEPS (300), WORKERS (host cores a data job),
# WINDOWS (512, eval_dynamics's), EVAL_EPISODES (64), TRAIN_FLAGS and EVAL_FLAGS (more flags). A CPU dry run:
# PLANNED=0 EPISODES=10 STEPS=3 SPEED_STEPS=2 WINDOWS=4 EVAL_EPISODES=2 GPUS=1 WORKERS=2 TRAIN_FLAGS="--batch 4 --hidden 16 --warmup 0"
# DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0 --image-size 64" EVAL_FLAGS="--quick --mpc-steps 1".
set -uo pipefail
WORK=${WORK:-/tmp/judge}; EPISODES=${EPISODES:-1536}; STEPS=${STEPS:-16000}; BOX=${BOX:-40}
SPEED_STEPS=${SPEED_STEPS:-300}; WINDOWS=${WINDOWS:-512}; WORKERS=${WORKERS:-$(nproc)}
EVAL_EPISODES=${EVAL_EPISODES:-64}
read -ra train_flags <<< "${TRAIN_FLAGS:-}"; read -ra eval_flags <<< "${EVAL_FLAGS:-}"
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || echo 1)}
SHIPPED=dynres_jax/checkpoints/dynamics
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"

log "start: $EPISODES episodes a set, $STEPS judge steps on $gpus GPUs, $WORKERS cores"
for i in 1 2 3; do gen "R$i" "3$i" 128 "$WORKERS"; done
data=("$WORK/data/R1" "$WORK/data/R2" "$WORK/data/R3")
if [ "${PLANNED:-1}" != 0 ]; then gen P 35 64 "$WORKERS" --planned 0.5; data+=("$WORK/data/P"); fi
pack

for n in $(printf "%s\n" 1 2 "$gpus" | sort -nu); do  # throughput: the same recipe on n GPUs
  [ "$n" -le "$gpus" ] && [ ! -f "$WORK/runs/speed$n/metrics.jsonl" ] || continue
  CUDA_VISIBLE_DEVICES=$(seq -s, 0 $((n - 1))) python -m experiments.train_dynamics --recipe judge \
    --data "${data[@]}" --out "$WORK/runs/speed$n" --steps "$SPEED_STEPS" --eval-every "$SPEED_STEPS" --warmup 0 --quiet \
    "${train_flags[@]}" > "$WORK/logs/speed$n.log" 2>&1
  log "speed on $n GPUs: $(tail -1 "$WORK/runs/speed$n/metrics.jsonl")"
done
pack

if [ ! -f "$WORK/runs/judge/done" ]; then
  log "train the judge"
  python -m experiments.train_dynamics --recipe judge --data "${data[@]}" --out "$WORK/runs/judge" --steps "$STEPS" \
    --max-minutes "$BOX" --quiet "${train_flags[@]}" > "$WORK/logs/train_judge.log" 2>&1 &&
    touch "$WORK/runs/judge/done"
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

if [ ! -f "$WORK/runs/loop/summary.json" ]; then
  log "closed loop: M&M Gather, the model against the judge"
  python -m experiments.evaluate --task gather --kind mnm --methods 50 judge --judge "$WORK/runs/judge/ckpt" \
    --episodes "$EVAL_EPISODES" --seed 7000 --out "$WORK/runs/loop" "${eval_flags[@]}" > "$WORK/logs/loop.log" 2>&1
  log "loop: $(grep -m2 -E '^ *(50|judge)' "$WORK/logs/loop.log" | tr '\n' ' ')"
fi
pack
touch "$WORK/done"
log "done"
