#!/usr/bin/env bash
# How many pushes Redistribute and Sort need (issue 66): evaluate on a 2-GPU host, every run recording each MPC step's
# scores and seen share, so that any shorter episode (the first T steps: an MPC step's keys depend on the step alone)
# and any stop share (`tasks.stopped`) is replayed offline by scripts/stop_rule.py --steps. Two calls:
#   PART=tune:  GPU 0 Redistribute tuning, F 2 O 7, seeds 70000- (128 episodes); GPU 1 Sort tuning, seeds 62000-
#               (32 a pair, three processes).
#   PART=fresh: Redistribute fresh, the twelve unseen characters, seeds $FRESH- (256, one process a GPU).
# Results under $OUT/{redistribute_tune,sort_tune,redistribute_fresh}/variants.tar.gz.
#   OUT=/tmp/w STEPS=100 PART=tune bash scripts/gpu_steps.sh
set -uo pipefail
OUT=${OUT:-runs/steps}; STEPS=${STEPS:-100}; SORT_STEPS=${SORT_STEPS:-60}; FRESH=${FRESH:-77000}; PART=${PART:-tune}
export METHODS=50
if [ "$PART" = tune ]; then
  FIRST_GPU=0 GPUS=1 OUT=$OUT/redistribute_tune TASK=redistribute EPISODES=${TUNE_EPISODES:-128} SEED=70000 \
    STEPS=$STEPS FLAGS="--letters F2O7" bash scripts/gpu_variants.sh &
  FIRST_GPU=1 GPUS=1 OUT=$OUT/sort_tune TASK=sort EPISODES=${SORT_EPISODES:-32} SEED=62000 STEPS=$SORT_STEPS \
    bash scripts/gpu_variants.sh &
else
  FIRST_GPU=0 GPUS=2 SPLIT=2 OUT=$OUT/redistribute_fresh TASK=redistribute EPISODES=${FRESH_EPISODES:-256} \
    SEED=$FRESH STEPS=$STEPS FLAGS="--letters BDGPQV345689" bash scripts/gpu_variants.sh &
fi
wait
