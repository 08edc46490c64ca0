#!/usr/bin/env bash
# Issue 65 on one host of several GPUs, in calls of at most 10 minutes that resume on a warm machine: data for the
# judge, its training throughput on 1 and 2 GPUs, the judge trained (--recipe judge, data-parallel over every GPU),
# its one- and five-step errors beside the shipped model's on held-out episodes, and the closed loop.
#   UNTIL=$(( $(date +%s) + 560 )) WORK=/tmp/judge bash scripts/gpu_judge.sh     # a 4-GPU host, 64 cores; repeat
# Data (C MuJoCo, one set a GPU at once): R1..R3, EPISODES random episodes each (seeds 31-33); P, P_EPISODES
# episodes where half the pushes are the shipped model's plans (seed 35; PLANNED=0: none). The errors: R1's
# validation episodes (every 10th; never trained on). Throughput: SPEED_STEPS steps of the recipe on 1 GPU and on 2, side by side
# on disjoint GPUs (metrics.jsonl's samples_per_s: windows of 5 pushes a second); all GPUs: the judge's own run.
# The judge: STEPS steps (default: what TRAIN_MINUTES of training at the probed speed allow, written to $WORK/steps
# and kept), stopping a minute before UNTIL (epoch seconds; the call's end) and going on in the next call.
# Closed loop: evaluate --methods 50 judge on M&M Gather, EVAL_EPISODES episodes from seed 7000 (tuning seeds: the
# headline is measured once, later, on fresh ones), 50 samples x 100 Adam steps, one GPU (32 episodes x 2 methods
# took 85 s on an H100).
# $WORK/results.tar.gz (logs, metrics, no data or checkpoints) and judge_ckpt.tar.gz (the judge's newest step) are
# rewritten after every stage, and copied to $OUT where set. A stage whose output exists is skipped.
# Env: WORK, UNTIL, PLANNED, EPISODES (1536), P_EPISODES (512), STEPS, TRAIN_MINUTES (9), SPEED_STEPS
# (100), WORKERS (host cores in all), WINDOWS (512), EVAL_EPISODES (64), TRAIN_FLAGS, EVAL_FLAGS, DATA_FLAGS. CPU dry
# run: PLANNED=0 EPISODES=10 P_EPISODES=4 STEPS=3 SPEED_STEPS=2 WINDOWS=4 EVAL_EPISODES=2 GPUS=1 WORKERS=2
# TRAIN_FLAGS="--batch 4 --hidden 16 --warmup 0" DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0
# --image-size 64" EVAL_FLAGS="--quick --mpc-steps 1 --best-omega 10 --samples 4 --adam-steps 2 --pieces 40".
set -uo pipefail
WORK=${WORK:-/tmp/judge}; EPISODES=${EPISODES:-1536}; P_EPISODES=${P_EPISODES:-512}
TRAIN_MINUTES=${TRAIN_MINUTES:-9}; SPEED_STEPS=${SPEED_STEPS:-100}; WINDOWS=${WINDOWS:-512}
WORKERS=${WORKERS:-$(nproc)}; EVAL_EPISODES=${EVAL_EPISODES:-64}; UNTIL=${UNTIL:-$(( $(date +%s) + 3600 ))}
read -ra train_flags <<< "${TRAIN_FLAGS:-}"; read -ra eval_flags <<< "${EVAL_FLAGS:-}"
SHIPPED=dynres_jax/checkpoints/dynamics
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"

pack_all() {  # logs and runs (no data, no checkpoints), the judge's newest checkpoint: to $OUT where set
  pack --exclude='*/ckpt'
  local step
  step=$(ls "$WORK/runs/judge/ckpt" 2>/dev/null | grep -E '^[0-9]+$' | sort -n | tail -1)
  [ -n "$step" ] && tar -czf "$WORK/judge.tmp" -C "$WORK/runs/judge" ckpt/"$step" && mv "$WORK/judge.tmp" "$WORK/judge_ckpt.tar.gz"
  [ -n "${OUT:-}" ] && cp "$WORK"/results.tar.gz "$WORK"/judge_ckpt.tar.gz "$OUT"/ 2>/dev/null
  return 0
}

log "call: $gpus GPUs, $WORKERS cores, $(( UNTIL - $(date +%s) )) s to go"
w=$(( WORKERS / 4 )); [ "$w" -ge 1 ] || w=1
(on 0; gen R1 31 128 "$w") &
(on 1; gen R2 32 128 "$w") &
(on 2; gen R3 33 128 "$w") &
data=("$WORK/data/R1" "$WORK/data/R2" "$WORK/data/R3")
if [ "${PLANNED:-1}" != 0 ]; then (on 3; EPISODES=$P_EPISODES gen P 35 64 "$w" --planned 0.5) & data+=("$WORK/data/P"); fi
wait
pack_all

speed() {  # N DEVICES: SPEED_STEPS steps of the recipe on N GPUs
  [ "$1" -le "$gpus" ] && [ ! -f "$WORK/runs/speed$1/metrics.jsonl" ] || return 0
  CUDA_VISIBLE_DEVICES=$2 python -m experiments.train_dynamics --recipe judge --data "${data[@]}" \
    --out "$WORK/runs/speed$1" --steps "$SPEED_STEPS" --eval-every "$SPEED_STEPS" --warmup 0 --quiet \
    "${train_flags[@]}" > "$WORK/logs/speed$1.log" 2>&1
  rm -rf "$WORK/runs/speed$1/ckpt"
  log "speed on $1 GPUs: $(tail -1 "$WORK/runs/speed$1/metrics.jsonl")"
}
speed 1 0 & speed 2 1,2 & wait
if [ ! -f "$WORK/steps" ]; then  # the cosine schedule's length: TRAIN_MINUTES at the probed speed on every GPU
  if [ -n "${STEPS:-}" ]; then echo "$STEPS" > "$WORK/steps"; else python - "$WORK" "$gpus" "$TRAIN_MINUTES" <<'PY' > "$WORK/steps"
import json, sys, glob
work, gpus, minutes = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rows = [json.loads(open(p).read().splitlines()[-1]) for p in glob.glob(f"{work}/runs/speed*/metrics.jsonl")]
rate = max(r["samples_per_s"] / r["devices"] for r in rows) * gpus * 0.9  # windows/s on every GPU, 90 % scaling
print(max(1000, int(minutes * 60 * rate / 128) // 1000 * 1000))
PY
  fi
  log "judge steps: $(cat "$WORK/steps")"
fi
pack_all

if [ ! -f "$WORK/runs/judge/done" ]; then
  left=$(python -c "print(round(($UNTIL - $(date +%s) - 75) / 60, 2))")
  if python -c "import sys; sys.exit(not $left > 1)"; then
    log "train the judge, $left minutes this call"
    unset CUDA_VISIBLE_DEVICES
    python -m experiments.train_dynamics --recipe judge --data "${data[@]}" --out "$WORK/runs/judge" \
      --steps "$(cat "$WORK/steps")" --max-minutes "$left" --quiet "${train_flags[@]}" \
      >> "$WORK/logs/train_judge.log" 2>&1
    last=$(tail -1 "$WORK/runs/judge/metrics.jsonl")
    log "judge: $last"
    python -c "import json,sys; sys.exit(json.loads(sys.argv[1])['step'] < $(cat "$WORK/steps"))" "$last" &&
      touch "$WORK/runs/judge/done"
  fi
fi
pack_all
[ -f "$WORK/runs/judge/done" ] || { log "the judge goes on in the next call"; exit 0; }

for m in "$SHIPPED" "$WORK/runs/judge/ckpt"; do
  name=$([ "$m" = "$SHIPPED" ] && echo shipped || echo judge)
  [ -f "$WORK/runs/eval/$name/eval.json" ] && continue
  (on 0; python -m experiments.eval_dynamics --ckpt "$m" --data "$WORK/data/R1" --out "$WORK/runs/eval/$name" \
    --windows "$WINDOWS" > "$WORK/logs/eval_$name.log" 2>&1)
  log "eval $name: $(tail -3 "$WORK/logs/eval_$name.log" | head -1)"
done
pack_all

if [ ! -f "$WORK/runs/loop/summary.json" ]; then
  log "closed loop: M&M Gather, the model against the judge"
  (on 0; python -m experiments.evaluate --task gather --kind mnm --methods 50 judge --judge "$WORK/runs/judge/ckpt" \
    --episodes "$EVAL_EPISODES" --seed 7000 --samples 50 --out "$WORK/runs/loop" "${eval_flags[@]}" \
    > "$WORK/logs/loop.log" 2>&1)
  log "loop: $(grep -E '^ *(50|judge)[: -]' "$WORK/logs/loop.log" | tr '\n' ' ')"
fi
pack_all
touch "$WORK/done"
log "done"
