#!/usr/bin/env bash
# The robot loop on one GPU machine against the closed-loop evaluation (issue 38, docs/robot), about 5 minutes:
#   OUT=runs/robot bash scripts/gpu_robot.sh
# 1. experiments.evaluate --sensor realsense: EPISODES Gather episodes at ω = 50 (50 x 100), seed SEED.
# 2. studies.robot_episodes: the same episodes through control.robot.run_robot (the simulator as a RealSense and an
#    arm, calibrated from each first frame, stopping at the goal as its frames show it), WORKERS processes, paired
#    with step 1.
# Env: OUT, EPISODES (64), SEED (7100), KIND (coffee), WORKERS (12), FLAGS (more flags for both, e.g. "--samples 4
# --adam-steps 5" with EVAL_FLAGS="--mpc-steps 2" and ROBOT_FLAGS="--steps 2" for a CPU dry run).
set -uo pipefail
OUT=${OUT:-runs/robot}; EPISODES=${EPISODES:-64}; SEED=${SEED:-7100}; KIND=${KIND:-coffee}; WORKERS=${WORKERS:-12}
mkdir -p "$OUT"
# shellcheck disable=SC2086
python -m experiments.evaluate --task gather --kind "$KIND" --episodes "$EPISODES" --methods 50 --sensor realsense \
  --seed "$SEED" --out "$OUT/evaluate" ${FLAGS:-} ${EVAL_FLAGS:-} > "$OUT/evaluate.log" 2>&1
echo "$(date +%T) evaluate: $(grep -m1 '50: final d' "$OUT/evaluate.log")"
# shellcheck disable=SC2086
python -m studies.robot_episodes --out "$OUT/robot" --episodes "$EPISODES" --seed "$SEED" --kind "$KIND" \
  --workers "$WORKERS" --evaluate "$OUT/evaluate" ${FLAGS:-} ${ROBOT_FLAGS:-} > "$OUT/robot.log" 2>&1
tail -3 "$OUT/robot.log"
