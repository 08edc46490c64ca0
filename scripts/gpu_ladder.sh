#!/usr/bin/env bash
# Issue 35's ladder on one GPU machine (runs in $WORK/KIND and $WORK/KIND-sim, all of them packed into
# $OUT/results.tar.gz after each run, so a run stopped by a time limit returns what finished): METHODS (default the model planner
# at ω = 50; add best5, oracle, ...) on EPISODES episodes, then the `sim` ceiling (the planner's 50 first samples
# scored in the simulator, no model) on the first SIM_EPISODES of the same episodes (episode i has the same pile and
# goal in both runs: paired). 50 samples x 100 Adam steps, no time budget; kinds in the order given, results written
# as they come.
#   OUT=runs/ladder bash scripts/gpu_ladder.sh                                    # Gather, every kind
#   OUT=runs/ladder-letters TASK=redistribute KINDS=coffee LETTERS=JTULY bash scripts/gpu_ladder.sh
# Env: TASK (gather), KINDS (all six), SIM_KINDS (the kinds that get the ceiling; default KINDS; "" for none),
# METHODS ("50"), EPISODES (64), SIM_EPISODES (16), LETTERS (Redistribute's goals, JTU), SEED (5000: seeds the project
# had not used), FLAGS (more evaluate flags: --ckpt DIR, ...), WORK (/tmp/ladder).
set -uo pipefail
OUT=${OUT:-runs/ladder}; WORK=${WORK:-/tmp/ladder}; EPISODES=${EPISODES:-64}; SIM_EPISODES=${SIM_EPISODES:-16}; SEED=${SEED:-5000}
TASK=${TASK:-gather}; METHODS=${METHODS:-50}; LETTERS=${LETTERS:-JTU}
KINDS=${KINDS:-coffee almond rice mnm granola candy}; SIM_KINDS=${SIM_KINDS-$KINDS}
run() {  # KIND "METHODS" EPISODES FOLDER
  # shellcheck disable=SC2086
  python -m experiments.evaluate --task "$TASK" --kind "$1" --episodes "$3" --methods $2 --samples 50 \
    --adam-steps 100 --seed "$SEED" --letters "$LETTERS" ${FLAGS:-} --out "$WORK/$4" 2>&1 | grep -v "it/s\]" | tail -4
  rm -rf "$WORK/$4/parts"
  mkdir -p "$OUT" && tar -czf "$OUT/results.tmp" -C "$WORK" . && mv "$OUT/results.tmp" "$OUT/results.tar.gz"
}
for kind in $KINDS; do run "$kind" "$METHODS" "$EPISODES" "$kind"; done
for kind in $SIM_KINDS; do run "$kind" sim "$SIM_EPISODES" "$kind-sim"; done
