"""The repeat recipe's report (scripts/recipes/repeat.toml): each run of OUT (its 50.json) with its seconds, success
and mean final distance, and each pair of runs' largest final-distance difference; into OUT/repeat.json.

    python scripts/repeat_report.py OUT
"""

import itertools
import json
import os
import sys

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
