#!/usr/bin/env bash
# Issue 36's on-policy question on one GPU machine: does a model trained on half random, half on-policy data
# (learn.on_policy) do better in closed loop than one trained on the same amount of random data?
#   CKPTS=".ckpt/r2/ckpt .ckpt/r4/ckpt" WORK=/tmp/op bash scripts/gpu_on_policy.sh
# 1. Data, two processes at once: R1 (random, seed 11, as gpu_model_at_scale.sh makes it) and P (on-policy: half the
#    pushes the closed loop's planner chooses on the shipped model, seed 15), EPISODES each.
# 2. r1p: --recipe shipped on R1 + P, STEPS steps (gpu_model_at_scale.sh's r2 is the same size on R1 + R2).
# 3. Closed loop (scripts/gpu_ladder.sh, ω = 50, 50 x 100, seeds from 5000): Gather M&M and Redistribute (JTULY),
#    COUNT episodes each, for every checkpoint of CKPTS while the data is made, then for r1p.
# Results: $WORK/out/lane*.tar.gz (closed loop), $WORK/results.tar.gz (logs, r1p's run folder); $WORK/done at the end.
# Env: WORK (/tmp/op), EPISODES (1536), STEPS (14000), COUNT (64), CKPTS (checkpoints compared with r1p), POLICY (the
# checkpoint P's pushes are planned with; default the shipped one), WORLDS
# (R1's and P's shard sizes: "128 64"), DATA_FLAGS (more generate_data flags), FLAGS (more evaluate flags). A CPU dry
# run: EPISODES=10 WORLDS="5 5" STEPS=20 COUNT=1 DATA_FLAGS="--kinds coffee --pieces 20 20 --two-kinds 0
# --image-size 64" FLAGS="--quick --samples 4 --adam-steps 2 --mpc-steps 1".
set -uo pipefail
WORK=${WORK:-/tmp/op}; EPISODES=${EPISODES:-1536}; STEPS=${STEPS:-14000}; BOX=${BOX:-11}; COUNT=${COUNT:-64}; CKPTS=${CKPTS:-}
read -r R_WORLDS P_WORLDS <<< "${WORLDS:-128 64}"
mkdir -p "$WORK/out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # data, training and two closed-loop lanes share the GPU
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"

ladder() {  # NAME LANE_A LANE_B CKPT...: Gather M&M on lane A, Redistribute on lane B, per checkpoint
  local name=$1 a=$2 b=$3 jobs=$WORK/$1.jobs; shift 3
  : > "$jobs"
  for c in "$@"; do echo "$a gather mnm 50 $COUNT $c" >> "$jobs"; echo "$b redistribute coffee 50 $COUNT $c" >> "$jobs"; done
  OUT=$WORK/out WORK=$WORK/ladder JOBS=$jobs bash scripts/gpu_ladder.sh > "$WORK/logs/ladder_$name.log" 2>&1
  log "closed loop $name: $(grep -c done "$WORK/logs/ladder_$name.log") jobs done"
}

log "start"
# shellcheck disable=SC2086
[ -n "$CKPTS" ] && ladder before 0 1 $CKPTS &
gen R1 11 "$R_WORLDS" 6 &
random=$!
gen P 15 "$P_WORLDS" 10 --planned 0.5 --policy "${POLICY:-shipped}"
wait "$random"
train r1p R1 P
pack
ladder after 2 3 "$WORK/runs/r1p/ckpt"
wait
pack
log "done"
touch "$WORK/done"
