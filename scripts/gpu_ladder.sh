#!/usr/bin/env bash
# Issue 35's ladder for Gather on every piece kind, one GPU machine (results in $OUT/KIND and $OUT/KIND-sim): the
# model planner at ω = 50 (50 samples x 100 Adam steps, no time budget) on EPISODES episodes, then the `sim` ceiling
# (the planner's 50 first samples scored in the simulator, no model) on the first SIM_EPISODES of the same episodes
# (episode i has the same pile and goal in both runs: paired). Kinds in the order given, results written as they come.
#   OUT=runs/ladder bash scripts/gpu_ladder.sh
# Env: KINDS (all six), SIM_KINDS (the kinds that get the ceiling; default KINDS), EPISODES (64), SIM_EPISODES (16),
# SEED (5000: seeds the project had not used), FLAGS (more evaluate flags: --ckpt DIR, ...).
set -uo pipefail
OUT=${OUT:-runs/ladder}; EPISODES=${EPISODES:-64}; SIM_EPISODES=${SIM_EPISODES:-16}; SEED=${SEED:-5000}
KINDS=${KINDS:-coffee almond rice mnm granola candy}; SIM_KINDS=${SIM_KINDS:-$KINDS}
run() {  # KIND METHOD EPISODES FOLDER
  # shellcheck disable=SC2086
  python -m experiments.evaluate --task gather --kind "$1" --episodes "$3" --methods "$2" --samples 50 \
    --adam-steps 100 --seed "$SEED" ${FLAGS:-} --out "$OUT/$4" 2>&1 | grep -v "it/s\]" | tail -1
  rm -rf "$OUT/$4/parts"
}
for kind in $KINDS; do run "$kind" 50 "$EPISODES" "$kind"; done
for kind in $SIM_KINDS; do run "$kind" sim "$SIM_EPISODES" "$kind-sim"; done
(cd "$OUT" && tar -czf results.tar.gz --exclude=results.tar.gz ./*)
