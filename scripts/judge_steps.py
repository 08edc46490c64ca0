"""The judge recipe's schedule length (scripts/recipes/judge.toml): the steps that MINUTES of training take on every
GPU at the speed the probes measured (WORK/runs/speed*/metrics.jsonl; 90 % scaling, 128 windows a step), rounded down
to thousands, at least 1,000.

    python scripts/judge_steps.py WORK GPUS MINUTES > WORK/steps
"""

import glob
import json
import sys

work, gpus, minutes = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rows = [json.loads(open(p).read().splitlines()[-1]) for p in glob.glob(f"{work}/runs/speed*/metrics.jsonl")]
rate = max(r["samples_per_s"] / r["devices"] for r in rows) * gpus * 0.9  # windows/s on every GPU, 90 % scaling
print(max(1000, int(minutes * 60 * rate / 128) // 1000 * 1000))
