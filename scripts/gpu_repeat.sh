#!/usr/bin/env bash
# Run-to-run spread of a GPU evaluation and the cost of --deterministic (issue 39, "repeatable numbers"): the same
# seeds evaluated twice as usual and twice with --deterministic; Gather of almonds at ω = 50, 50 x 100 Adam steps (the
# case two evaluations once put at 36 % and 55 %). Results in $OUT/RUN; $OUT/repeat.json compares the runs present.
#   OUT=runs/repeat RUNS="plain-1 plain-2" bash scripts/gpu_repeat.sh
set -uo pipefail
OUT=${OUT:-runs/repeat}; EPISODES=${EPISODES:-32}; SEED=${SEED:-3000}; KIND=${KIND:-almond}
for run in ${RUNS:-plain-1 plain-2 deterministic-1 deterministic-2}; do
  flag=""; [[ $run == deterministic-* ]] && flag="--deterministic"
  # shellcheck disable=SC2086
  python -m experiments.evaluate --task gather --kind "$KIND" --episodes "$EPISODES" --methods 50 --samples 50 \
    --adam-steps 100 --seed "$SEED" $flag --out "$OUT/$run" 2>&1 | grep -v "it/s\]" | tail -2 || exit
  rm -rf "$OUT/$run/parts"
done
python - "$OUT" <<'PY'
import itertools, json, os, sys

import numpy as np

out = sys.argv[1]
runs = {r: json.load(open(os.path.join(out, r, "50.json"))) for r in sorted(os.listdir(out))
        if os.path.exists(os.path.join(out, r, "50.json"))}
report = {r: dict(seconds=v["seconds"], success=float(np.mean(np.array(v["final_inside"]) >= 0.9 - 1e-6)),
                  final_distance=float(np.mean(v["final_distance"]))) for r, v in runs.items()}
pairs = {f"{a} vs {b}": dict(max_abs_d=float(np.max(np.abs(np.subtract(runs[a]["final_distance"],
                                                                       runs[b]["final_distance"])))),
                             episodes_differing=int(np.sum(np.array(runs[a]["final_distance"])
                                                           != np.array(runs[b]["final_distance"]))))
         for a, b in itertools.combinations(runs, 2)}
json.dump(dict(runs=report, pairs=pairs), open(os.path.join(out, "repeat.json"), "w"), indent=1)
print(json.dumps(dict(runs=report, pairs=pairs), indent=1))
PY
