#!/usr/bin/env bash
# Dynamics models end to end on one GPU machine: one data set (C MuJoCo on every host core, frames rendered on the
# GPU), then every variant trained side by side (a time-boxed run whose step count is set from the speed it measures;
# variant i on GPU i mod the GPU count, so a machine with several GPUs shares each among fewer), then its held-out
# evaluation. Each variant's run folder is packed as $OUT/NAME.tar.gz (its log too).
#   OUT=runs/ship bash scripts/ship_dynamics.sh                 # one variant, "dynamics", with MODEL_FLAGS
#   OUT=runs/ship VARIANTS="gnn:--residual --push-frame;cnn:--model cnn" bash scripts/ship_dynamics.sh
# Env: EPISODES (2000), DATA_FLAGS (more generate_data flags), TRAIN_MINUTES (4), STEPS (every
# variant trains exactly this many steps, the box only a safety stop; default: as many as fill the box at the probed
# speed), BATCH (64), PROBE_STEPS (300), DATA (/tmp/piles), VARIANTS ("NAME:flags;NAME:flags", default
# "dynamics:$MODEL_FLAGS"), RUNS (run folders, default $OUT):
# $RUNS/NAME/{ckpt,metrics.jsonl,curves.png,eval/,timing.json} and $RUNS/NAME.log (outside the run folder, which
# train_dynamics claims: it must be new or its own).
set -euo pipefail
OUT=${OUT:-runs/ship}; DATA=${DATA:-/tmp/piles}; RUNS=${RUNS:-$OUT}
EPISODES=${EPISODES:-2000}; TRAIN_MINUTES=${TRAIN_MINUTES:-4}; BATCH=${BATCH:-64}; PROBE=${PROBE_STEPS:-300}
VARIANTS=${VARIANTS:-"dynamics:${MODEL_FLAGS:-}"}
mkdir -p "$OUT"
t0=$(date +%s)
# shellcheck disable=SC2086
python -m experiments.generate_data --out "$DATA" --backend mujoco --episodes "$EPISODES" --pushes 10 --worlds 64 \
  ${DATA_FLAGS:-} --no-progress > "$OUT/data_summary.json"
cat "$OUT/data_summary.json"
t1=$(date +%s)
echo "{\"data_s\": $((t1 - t0))}" > "$OUT/timing.json"

variant() {  # NAME FLAGS: probe the speed, train to the time box, evaluate, pack
  local name=$1 flags=$2 run=$RUNS/$1 steps t2 t3
  # PROBE steps to measure the speed (the cosine schedule's length may change on resume), then the rest of the budget:
  # the steps that fill 95 % of the box less 25 s at that speed (samples/s leaves out compiling, validation and
  # checkpoints: the 25 s pays for the compile, the 5 % for the rest), so the schedule runs to its end inside the box
  # (measured: 3 min boxes ran to the end with three runs sharing an H100; 1.4 min ones stopped at 75-80 % of a
  # 15 %-margin plan).
  # shellcheck disable=SC2086
  python -m experiments.train_dynamics --data "$DATA" --out "$run" --batch "$BATCH" $flags --steps "$PROBE" \
    --eval-every "$PROBE" --quiet
  steps=${STEPS:-$(python - "$run" "$TRAIN_MINUTES" "$PROBE" <<'PY'
import json, sys
from dynres_jax.io import ckpt
rate = json.loads(open(sys.argv[1] + "/metrics.jsonl").readlines()[-1])["samples_per_s"]
batch = ckpt.load_meta(sys.argv[1] + "/ckpt")["train"]["batch"]  # the variant's own --batch, if it has one
print(int(0.95 * rate * max(60 * float(sys.argv[2]) - 25, 0) / batch) // 100 * 100 + int(sys.argv[3]))
PY
)}
  echo "$name: training to $steps steps"
  t2=$(date +%s)
  # shellcheck disable=SC2086
  python -m experiments.train_dynamics --data "$DATA" --out "$run" --batch "$BATCH" $flags --steps "$steps" \
    --max-minutes "$TRAIN_MINUTES" --quiet
  t3=$(date +%s)
  python -m experiments.eval_dynamics --ckpt "$run/ckpt" --data "$DATA" --out "$run/eval"
  echo "{\"name\": \"$name\", \"flags\": \"$flags\", \"train_s\": $((t3 - t2)), \"eval_s\": $(($(date +%s) - t3))}" \
    > "$run/timing.json"
}

IFS=';' read -ra specs <<< "$VARIANTS"
gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true); gpus=$((gpus > 0 ? gpus : 1))
# Side by side on a GPU: each process may take an equal share of its memory.
XLA_PYTHON_CLIENT_MEM_FRACTION=$(python -c "print(round(0.9 / -(-${#specs[@]} // $gpus), 3))")
export XLA_PYTHON_CLIENT_MEM_FRACTION
pids=()
for i in "${!specs[@]}"; do
  spec=${specs[$i]} name=${specs[$i]%%:*}
  mkdir -p "$RUNS"
  (set +e; export CUDA_VISIBLE_DEVICES=$((i % gpus))
   (set -e; variant "$name" "${spec#*:}" > "$RUNS/$name.log" 2>&1); rc=$?
   tar -czf "$OUT/$name.tar.gz" -C "$RUNS" "$name" "$name.log"; exit $rc) &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
for spec in "${specs[@]}"; do echo "== ${spec%%:*}"; tail -8 "$RUNS/${spec%%:*}.log"; done
exit $status
