#!/usr/bin/env bash
# A kind held out of training (issue 26), one GPU machine, one call: one C data set of all six kinds, two models
# trained side by side with the same recipe and steps, one on every kind ("all") and one that never sees KIND
# ("without"), each evaluated one step per kind on the held-out episodes (eval_dynamics) and closed loop on Gather of
# KIND (64 episodes, seeds 1000+, ω = 50). Results packed in $OUT/heldout.tar.gz.
#   OUT=runs/heldout KIND=candy bash scripts/gpu_heldout.sh       # Env: EPISODES (1024), STEPS (6000)
set -euo pipefail
OUT=${OUT:-runs/heldout}; KIND=${KIND:-candy}; EPISODES=${EPISODES:-1024}; STEPS=${STEPS:-6000}
F="--residual --push-frame --world-edges --loss distance --bin-position"
mkdir -p "$OUT" /tmp/heldout
OUT=/tmp/heldout RUNS=/tmp/heldout/runs DATA=/tmp/piles_all EPISODES=$EPISODES STEPS=$STEPS TRAIN_MINUTES=4 \
  VARIANTS="all:$F;without:$F --held-out-kinds $KIND" bash scripts/ship_dynamics.sh > "$OUT/train.log" 2>&1
for m in all without; do
  KINDS=$KIND FLAGS="--ckpt /tmp/heldout/runs/$m/ckpt" OUT=/tmp/heldout/gather_$m bash scripts/gpu_kinds.sh
done
tar -czf "$OUT/heldout.tar.gz" --exclude='*.gif' -C /tmp heldout
