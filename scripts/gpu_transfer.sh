#!/usr/bin/env bash
# Is MJX data as good as C data where it counts? One GPU machine, three calls (each fits the device tool's 10 minutes):
#   STAGE=c   OUT=runs/transfer bash scripts/gpu_transfer.sh   # C MuJoCo data (16 host cores) -> model "c"
#   STAGE=mjx OUT=runs/transfer bash scripts/gpu_transfer.sh   # MJX on the fast scene (the GPU) -> model "mjx"
#   STAGE=eval OUT=runs/transfer CKPTS=runs/transfer bash scripts/gpu_transfer.sh  # both, closed loop, C scene
# The data stages run scripts/ship_dynamics.sh with the same data config (the same shard scenes: coffee, 100 pieces,
# the three layouts) and the same training (a fixed number of steps), differing only in --backend; each packs its run
# as $OUT/NAME.tar.gz and writes the generation summary (pushes/s, compiles included) to $OUT/NAME_data.json.
# The eval stage unpacks CKPTS/{c,mjx}.tar.gz, makes a small held-out C data set for the one-step table
# (eval_dynamics), and runs Gather in the default (C) scene on 64 episodes, seeds 1000+, ω = 50, for both models.
#   STAGE=speed OUT=runs/transfer bash scripts/gpu_transfer.sh  # data generation at scale: one scene, compiled once
# The speed stage makes a larger run of one scene (coffee, 100 pieces, spread) with each engine: MJX on the fast scene
# (4,096 episodes, 1,024 worlds a shard) and C MuJoCo on every host core (512 episodes); $OUT/speed_{mjx,c}.json.
set -euo pipefail
OUT=${OUT:-runs/transfer}; EPISODES=${EPISODES:-1024}; STEPS=${STEPS:-8000}
mkdir -p "$OUT"
DATA_CONFIG="--kinds coffee --pieces 100 100 --two-kinds 0 --worlds 128"
F="--residual --push-frame --world-edges --loss distance --bin-position"
case ${STAGE:?STAGE is c, mjx, eval or speed} in
  c | mjx)
    backend=$([ "$STAGE" = c ] && echo mujoco || echo mjx-fast)
    OUT=$OUT RUNS=/tmp/runs DATA=/tmp/piles_$STAGE EPISODES=$EPISODES STEPS=$STEPS TRAIN_MINUTES=5 \
      DATA_FLAGS="$DATA_CONFIG --backend $backend" VARIANTS="$STAGE:$F" bash scripts/ship_dynamics.sh
    cp "$OUT/data_summary.json" "$OUT/${STAGE}_data.json"
    ;;
  eval)
    for m in c mjx; do tar -xzf "${CKPTS:?}/$m.tar.gz" -C /tmp; done
    python -m experiments.generate_data --out /tmp/heldout --backend mujoco --episodes 128 --pushes 10 --worlds 64 \
      --kinds coffee --pieces 100 100 --two-kinds 0 --seed 7 --no-progress > "$OUT/heldout_data.json"
    for m in c mjx; do
      python -m experiments.eval_dynamics --ckpt "/tmp/$m/ckpt" --data /tmp/heldout --out "$OUT/onestep_$m" \
        > "$OUT/onestep_$m.log" 2>&1
      python -m experiments.evaluate --task gather --methods 50 --episodes 64 --seed 1000 --ckpt "/tmp/$m/ckpt" \
        --out "$OUT/gather_$m" > "$OUT/gather_$m.log" 2>&1
      tail -3 "$OUT/gather_$m.log"
    done
    ;;
  speed)
    rm -rf /tmp/speed_mjx /tmp/speed_c  # a fresh run each time: a finished one would resume to nothing
    one_scene="--kinds coffee --pieces 100 100 --two-kinds 0 --layouts spread --pushes 10 --no-progress"
    # shellcheck disable=SC2086
    python -m experiments.generate_data --out /tmp/speed_mjx --backend mjx-fast --episodes 4096 --worlds 1024 \
      $one_scene > "$OUT/speed_mjx.json"
    # shellcheck disable=SC2086
    python -m experiments.generate_data --out /tmp/speed_c --backend mujoco --episodes 512 --worlds 128 \
      $one_scene > "$OUT/speed_c.json"
    grep -h '"samples_per_s"\|"seconds"\|"backend"' "$OUT"/speed_*.json
    ;;
  *) echo "STAGE is c, mjx, eval or speed" >&2; exit 2 ;;
esac
