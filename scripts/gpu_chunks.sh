#!/usr/bin/env bash
# Episodes independent of their batch (issue 70 item 7) and what it costs: evaluate's Gather (ω = 50, 50 x 100 Adam
# steps, STEPS MPC steps) on EPISODES episodes and on the first FEW of them, for each source tree of SOURCES (a
# checkout's root, run from there: e.g. a copy of main beside this branch), one run at a time on the GPU.
# $OUT/chunks.json: per source, the seconds of each run (its steps' and the process's wall time), how many of the
# FEW episodes ended differently (final d, final piece positions) in the large run than alone, and the large runs'
# time ratio against the first source's. FLAGS: more evaluate flags (a CPU dry run: EPISODES=3 FEW=1 STEPS=1
# FLAGS="--quick --samples 4 --adam-steps 2").
#   OUT=runs/chunks SOURCES="/tmp/main ." bash scripts/gpu_chunks.sh
#   (two GPUs: CUDA_VISIBLE_DEVICES=0 SOURCES=/tmp/main ... & CUDA_VISIBLE_DEVICES=1 SOURCES=. ... & wait; then both)
set -uo pipefail
OUT=${OUT:-runs/chunks}; OUT=$(mkdir -p "$OUT" && cd "$OUT" && pwd)  # absolute: the runs start in each source
EPISODES=${EPISODES:-256}; FEW=${FEW:-32}; STEPS=${STEPS:-10}; SEED=${SEED:-71000}
SOURCES=${SOURCES:-.}; KIND=${KIND:-coffee}
names=()
for src in $SOURCES; do
  name=$(basename "$(cd "$src" && pwd)"); names+=("$name")
  for n in "$EPISODES" "$FEW"; do
    [ -f "$OUT/$name-$n.wall" ] && continue  # done: a rerun only reports (sources run side by side, then together)
    start=$(date +%s.%N)
    # shellcheck disable=SC2086
    (cd "$src" && python -m experiments.evaluate --task gather --kind "$KIND" --episodes "$n" --methods 50 \
      --samples 50 --adam-steps 100 --mpc-steps "$STEPS" --seed "$SEED" ${FLAGS:-} --out "$OUT/$name-$n" 2>&1 |
      grep -v "it/s\]" | tail -2)
    python -c "print($(date +%s.%N) - $start)" > "$OUT/$name-$n.wall"
  done
done
python - "$OUT" "$EPISODES" "$FEW" "${names[@]}" <<'PY'
import json, os, sys

import numpy as np

out, many, few, names = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:]
load = lambda name, n: json.load(open(os.path.join(out, f"{name}-{n}", "50.json")))
report = {}
for name in names:
    a, b = load(name, many), load(name, few)
    d = np.subtract(a["final_distance"][:few], b["final_distance"])
    pieces = [np.max(np.abs(np.subtract(x, y))) for x, y in zip(a["final_pieces"][:few], b["final_pieces"])]
    wall = lambda n: float(open(os.path.join(out, f"{name}-{n}.wall")).read())  # noqa: E731
    report[name] = dict(seconds_many=a["seconds"], seconds_few=b["seconds"], wall_many=wall(many), wall_few=wall(few),
                        episodes_differing_d=int(np.sum(d != 0)), max_abs_d=float(np.max(np.abs(d))),
                        episodes_differing_pieces=int(np.sum(np.array(pieces) > 0)))
for name in names:
    for k in ("seconds_many", "wall_many"):
        report[name][f"{k}_ratio"] = report[name][k] / report[names[0]][k]
json.dump(report, open(os.path.join(out, "chunks.json"), "w"), indent=1)
print(json.dumps(report, indent=1))
PY
