"""The judge_rank recipe's rule, fixed before any run (scripts/recipes/judge_rank.toml): of the judges NAME..., the one
with the most successes over both tuning tasks (WORK/runs/tune_{mnm,red}_NAME/summary.json), ties to the lower mean
final distance; its name on stdout, each judge's successes on stderr.

    python scripts/judge_choose.py WORK NAME... > WORK/chosen
"""

import json
import sys

work, names = sys.argv[1], sys.argv[2:]


def rows(name):
    s = [json.load(open(f"{work}/runs/tune_{t}_{name}/summary.json")) for t in ("mnm", "red")]
    return [m for x in s for m in [x["methods"]["judge"]]], [x["methods"]["50"] for x in s]


score = {}
for n in names:
    judge, model = rows(n)
    score[n] = (sum(m["success_share"] for m in judge), -sum(m["final_distance"] for m in judge))
    print(f"{n}: success {[m['success_share'] for m in judge]} (model {[m['success_share'] for m in model]})",
          file=sys.stderr)
print(max(names, key=lambda n: score[n]))
