#!/usr/bin/env bash
# Issue 36 on one GPU machine: data at scale, the scaling study's models, their held-out and noise-floor errors.
#   WORK=/tmp/scale bash scripts/gpu_model_at_scale.sh      # about 25 minutes on one H100 and 16 host cores
# Data (C MuJoCo on the host cores; frames rendered and on-policy pushes planned on the GPU), two processes at once:
#   R1..R4  random pushes (seeds 11-14), EPISODES each in shards of 128 worlds, on RANDOM_WORKERS processes
#   P       on-policy: half the pushes the closed loop's planner chooses on the shipped model (seed 15), EPISODES in
#           shards of 64 worlds (a planner batch of 64 x 50 sequences), on PLANNED_WORKERS processes
# Models (--recipe shipped, STEPS Adam steps at batch 64 each, validated every 2,000), each started once its data is
# there: r1 (R1), r2 (R1 R2), r4 (R1..R4), r3p (R1..R3 P: r4's size with a quarter on-policy), r4p (all),
# r4p-h128 (all, hidden 128: the capacity step).
# Evaluation: eval_dynamics of every model (and the shipped one) on R1's and on P's held-out episodes; studies.noise_floor
# (32 scenes x 8 worlds x 2 pushes, σ = 1 mm, seed 1: the noise floor's windows) of all of them on the same pushes.
# $WORK/results.tar.gz (metrics, evaluations, checkpoints, logs; no data) is rewritten after every stage, and
# $WORK/done marks the end. A stage whose output exists is skipped, so a rerun on a warm machine goes on.
# Env: WORK, EPISODES (1536), STEPS (14000), BOX (minutes, a safety stop for each training: 11), RANDOM_WORKERS (12),
# PLANNED_WORKERS (6: P plans on the GPU between pushes, so the two share the cores),
# RANDOM_WORLDS (128), PLANNED_WORLDS (64), DATA_FLAGS (more generate_data flags), WINDOWS (512, eval_dynamics's),
# FLOOR_FLAGS (the noise floor's sizes). A CPU dry run of the mechanics: EPISODES=10 RANDOM_WORLDS=5 PLANNED_WORLDS=5
# DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0 --image-size 64" STEPS=20 WINDOWS=8
# FLOOR_FLAGS="--scenes 1 --worlds 2 --pushes 1" RANDOM_WORKERS=1 PLANNED_WORKERS=1.
set -uo pipefail
WORK=${WORK:-/tmp/scale}; EPISODES=${EPISODES:-1536}; STEPS=${STEPS:-14000}; BOX=${BOX:-11}
RANDOM_WORKERS=${RANDOM_WORKERS:-12}; PLANNED_WORKERS=${PLANNED_WORKERS:-6}
RANDOM_WORLDS=${RANDOM_WORLDS:-128}; PLANNED_WORLDS=${PLANNED_WORLDS:-64}
WINDOWS=${WINDOWS:-512}; FLOOR_FLAGS=${FLOOR_FLAGS:-"--scenes 32 --worlds 8 --pushes 2"}
cores=$(nproc)
SHIPPED=dynres_jax/checkpoints/dynamics
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # a dozen processes share the GPU: each takes what it uses
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"

log "start: $EPISODES episodes per data set, $STEPS steps per model, $cores cores"
gen R1 11 "$RANDOM_WORLDS" "$RANDOM_WORKERS"
train r1 R1 &
(gen P 15 "$PLANNED_WORLDS" "$PLANNED_WORKERS" --planned 0.5) &
planned=$!
gen R2 12 "$RANDOM_WORLDS" "$RANDOM_WORKERS"
train r2 R1 R2 &
gen R3 13 "$RANDOM_WORLDS" "$RANDOM_WORKERS"
wait "$planned"
train r3p R1 R2 R3 P &
gen R4 14 "$RANDOM_WORLDS" "$cores"
pack
train r4 R1 R2 R3 R4 &
train r4p R1 R2 R3 R4 P &
train r4p-h128 R1 R2 R3 R4 P -- --hidden 128 &
wait
pack

log "evaluate"
models=("$SHIPPED")
for run in r1 r2 r3p r4 r4p r4p-h128; do [ -d "$WORK/runs/$run/ckpt" ] && models+=("$WORK/runs/$run/ckpt"); done
for m in "${models[@]}"; do
  name=$(basename "$(dirname "$m")"); [ "$m" = "$SHIPPED" ] && name=shipped
  for set in R1 P; do
    python -m experiments.eval_dynamics --ckpt "$m" --data "$WORK/data/$set" \
      --out "$WORK/runs/eval/$name-$set" --windows "$WINDOWS" > "$WORK/logs/eval_$name-$set.log" 2>&1 &
  done
done
# shellcheck disable=SC2086
python -m studies.noise_floor --out "$WORK/runs/floor" $FLOOR_FLAGS \
  --sigmas 1 --ckpt "${models[@]}" --no-progress > "$WORK/logs/floor.log" 2>&1
wait
log "done"
pack
touch "$WORK/done"
