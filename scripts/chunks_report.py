"""The chunks recipe's report (scripts/recipes/chunks.toml): per source, the seconds of its runs of MANY and FEW
episodes, how many of the FEW episodes ended differently in the large run than alone, and the large runs' time ratio
against the first source's; into OUT/chunks.json.

    python scripts/chunks_report.py OUT MANY FEW NAME...
"""

import json
import os
import sys

import numpy as np

out, many, few, names = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:]
load = lambda name, n: json.load(open(os.path.join(out, f"{name}-{n}", "50.json")))
report = {}
for name in names:
    a, b = load(name, many), load(name, few)
    d = np.subtract(a["final_distance"][:few], b["final_distance"])
    pairs = zip(a["final_pieces"][:few], b["final_pieces"], strict=False)
    pieces = [np.max(np.abs(np.subtract(x, y))) for x, y in pairs]
    wall = lambda n: float(open(os.path.join(out, f"{name}-{n}.wall")).read())  # noqa: B023
    report[name] = dict(seconds_many=a["seconds"], seconds_few=b["seconds"], wall_many=wall(many), wall_few=wall(few),
                        episodes_differing_d=int(np.sum(d != 0)), max_abs_d=float(np.max(np.abs(d))),
                        episodes_differing_pieces=int(np.sum(np.array(pieces) > 0)))
for name in names:
    for k in ("seconds_many", "wall_many"):
        report[name][f"{k}_ratio"] = report[name][k] / report[names[0]][k]
json.dump(report, open(os.path.join(out, "chunks.json"), "w"), indent=1)
print(json.dumps(report, indent=1))
