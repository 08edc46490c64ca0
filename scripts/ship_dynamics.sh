#!/usr/bin/env bash
# The shipped dynamics model, end to end on one GPU machine: data (C MuJoCo on every host core, frames rendered on
# the GPU), training (a time-boxed run whose step count is set from the measured speed), held-out evaluation.
#   OUT=runs/ship bash scripts/ship_dynamics.sh        # results in $OUT/dynamics, data in $DATA (default /tmp/piles)
# Env: EPISODES (2000), TRAIN_MINUTES (4), BATCH (64), PROBE_STEPS (300), MODEL_FLAGS (e.g. "--residual --push-frame").
set -euo pipefail
OUT=${OUT:-runs/ship}; DATA=${DATA:-/tmp/piles}
EPISODES=${EPISODES:-2000}; TRAIN_MINUTES=${TRAIN_MINUTES:-4}; BATCH=${BATCH:-64}; PROBE=${PROBE_STEPS:-300}
RUN=$OUT/dynamics
mkdir -p "$RUN"
t0=$(date +%s)
python -m experiments.generate_data --out "$DATA" --backend mujoco --episodes "$EPISODES" --pushes 10 --worlds 64 \
  --no-progress > "$RUN/data_summary.json"
cat "$RUN/data_summary.json"
t1=$(date +%s)
# PROBE steps to measure the speed (the cosine schedule's length may change on resume), then the rest of the budget.
python -m experiments.train_dynamics --data "$DATA" --out "$RUN" --batch "$BATCH" ${MODEL_FLAGS:-} --steps "$PROBE" --eval-every "$PROBE" --quiet
steps=$(python - "$RUN/metrics.jsonl" "$TRAIN_MINUTES" "$BATCH" "$PROBE" <<'PY'
import json, sys
rate = json.loads(open(sys.argv[1]).readlines()[-1])["samples_per_s"]
print(int(rate * 60 * float(sys.argv[2]) / int(sys.argv[3])) // 500 * 500 + int(sys.argv[4]))
PY
)
echo "training to $steps steps"
python -m experiments.train_dynamics --data "$DATA" --out "$RUN" --batch "$BATCH" ${MODEL_FLAGS:-} --steps "$steps" \
  --max-minutes "$TRAIN_MINUTES" --quiet
t2=$(date +%s)
python -m experiments.eval_dynamics --ckpt "$RUN/ckpt" --data "$DATA" --out "$RUN/eval"
t3=$(date +%s)
echo "{\"data_s\": $((t1 - t0)), \"train_s\": $((t2 - t1)), \"eval_s\": $((t3 - t2))}" > "$RUN/timing.json"
cat "$RUN/timing.json"
