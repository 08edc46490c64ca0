#!/usr/bin/env bash
# Scaling over the GPUs of one host (issue 28), each figure a whole job's wall time (start-up and compiles included):
# for every G in COUNTS (those up to the host's GPU count), data generation and labels as a jax.distributed job of G
# processes, one GPU each (process i makes shards i, i + G, ... of one folder), and training as one process that
# splits each batch over G GPUs (the same global batch for every G, so the models are comparable). One line per
# (stage, G) in $OUT/scaling.jsonl; the training runs' metrics in $OUT/train_G.jsonl.
#   OUT=runs/scaling bash scripts/gpu_scaling.sh
# Training uses the data the 1-GPU data stage made. A dry run of the mechanics on a CPU: GPUS=2 COUNTS="1 2"
# EPISODES=16 STEPS=4 BATCH=4 STAGES="data train" DATA_FLAGS="--quick --worlds 4 --pushes 5" JAX_PLATFORMS=cpu.
# Env: COUNTS ("1 2 4"), STAGES ("data labels train"), EPISODES (4096: 8 shards of 512 worlds), SCENES (256: labels,
# 4 shards of 64), STEPS (2000 training steps), BATCH (256), DATA_FLAGS (generate_data's scene and engine).
set -euo pipefail
OUT=${OUT:-runs/scaling}; COUNTS=${COUNTS:-"1 2 4"}; STAGES=${STAGES:-"data labels train"}
EPISODES=${EPISODES:-4096}; SCENES=${SCENES:-256}; STEPS=${STEPS:-2000}; BATCH=${BATCH:-256}
DATA_FLAGS=${DATA_FLAGS:-"--backend mjx-fast --kinds coffee --pieces 100 100 --two-kinds 0 --layouts spread --worlds 512"}
mkdir -p "$OUT"
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || true)}  # GPUS: override (a CPU dry run)
now() { python -c "import time; print(time.time())"; }
record() { echo "{\"stage\": \"$1\", \"gpus\": $2, \"seconds\": $3, \"per_s\": $4, \"unit\": \"$5\"}" | tee -a "$OUT/scaling.jsonl"; }

job() {  # G LOG MODULE ARGS...: a jax.distributed job of G processes, process i on GPU i
  local g=$1 log=$2 port=$((20000 + RANDOM % 20000)) pids=() i status=0
  shift 2
  for ((i = 0; i < g; i++)); do
    CUDA_VISIBLE_DEVICES=$i XLA_PYTHON_CLIENT_MEM_FRACTION=0.9 python -m "$@" --coordinator "localhost:$port" \
      --num-processes "$g" --process-id "$i" > "$log.$i" 2>&1 &
    pids+=($!)
  done
  for i in "${pids[@]}"; do wait "$i" || status=1; done
  return $status
}

for g in $COUNTS; do
  if [ "$gpus" -lt "$g" ]; then echo "skip $g GPUs: the host has $gpus"; continue; fi
  for stage in $STAGES; do
    rm -rf "/tmp/scaling_$stage"
    t0=$(now)
    case $stage in
      data)
        # shellcheck disable=SC2086
        job "$g" "$OUT/data_$g.log" experiments.generate_data --out /tmp/scaling_data --episodes "$EPISODES" \
          --pushes 10 --no-progress $DATA_FLAGS
        t1=$(now); s=$(python -c "print($t1 - $t0)")
        record data "$g" "$s" "$(python -c "import json; r = json.load(open('/tmp/scaling_data/summary.json'))
print(r['episodes'] * r['pushes'] / $s)")" "pushes/s"
        [ "$g" = 1 ] && rm -rf /tmp/scaling_train_data && mv /tmp/scaling_data /tmp/scaling_train_data ;;
      labels)
        job "$g" "$OUT/labels_$g.log" experiments.label_resolution --out /tmp/scaling_labels --scenes "$SCENES" \
          --batch 64 --time-budget 0.25 --backend mujoco --workers $((16 / g))
        t1=$(now); s=$(python -c "print($t1 - $t0)")
        record labels "$g" "$s" "$(python -c "print($SCENES * 60 / $s)")" "labels/min" ;;
      train)
        CUDA_VISIBLE_DEVICES=$(seq -s, 0 $((g - 1))) python -m experiments.train_dynamics \
          --data /tmp/scaling_train_data --out /tmp/scaling_train --recipe shipped --steps "$STEPS" --batch "$BATCH" \
          --eval-every "$STEPS" --quiet > "$OUT/train_$g.log" 2>&1
        t1=$(now); s=$(python -c "print($t1 - $t0)")
        cp /tmp/scaling_train/metrics.jsonl "$OUT/train_$g.jsonl"
        record train "$g" "$s" "$(python -c "import json; print(json.loads(open('$OUT/train_$g.jsonl').readlines()[-1])['samples_per_s'])")" "samples/s"
        rm -rf /tmp/scaling_train ;;
    esac
  done
done
