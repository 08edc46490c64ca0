#!/usr/bin/env bash
# Gather on every piece kind with the shipped model, one GPU machine (results in $OUT/KIND): each kind at its default
# count (DEFAULT_PIECES: a pile of 100 coffee beans' area), ω = 50, 50 samples x 100 Adam steps, no time budget.
#   OUT=runs/kinds bash scripts/gpu_kinds.sh
# Env: KINDS (all six), EPISODES (64), SEED (1000: seeds the project had not used when it was first run), SENSOR
# (none; realsense: the depth-camera profile of dynres_jax/sim/sensor.py), FLAGS (more evaluate flags: --ckpt DIR,
# --horizon 2, ...).
set -uo pipefail
OUT=${OUT:-runs/kinds}; EPISODES=${EPISODES:-64}; SEED=${SEED:-1000}; SENSOR=${SENSOR:-none}
# shellcheck disable=SC2086
for kind in ${KINDS:-coffee almond rice mnm granola candy}; do
  python -m experiments.evaluate --task gather --kind "$kind" --episodes "$EPISODES" --methods 50 --samples 50 \
    --adam-steps 100 --seed "$SEED" --sensor "$SENSOR" ${FLAGS:-} --out "$OUT/$kind" 2>&1 | grep -v "it/s\]" | tail -2 || exit
  rm -rf "$OUT/$kind/parts"
done
# one archive of every kind's results (a device run brings back only so many files)
(cd "$OUT" && tar -czf results.tar.gz --exclude=results.tar.gz ./*)
