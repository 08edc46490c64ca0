"""Recorded behaviour of the closed loop: seeded runs of Gather (fixed ω; adaptive under a frozen time budget),
Redistribute, Sort and a small evaluation, reduced to what must not change when the loop's code is reorganised
(the pushes, ω, buckets, Adam steps, c, predicted c, d, the inside share, Sort's scores, evaluate's summary).

    python tests/loop_reference.py            # write tests/data/loop_reference.json from the code as it is

tests/test_loop_reference.py runs the same commands and compares. Wall times are left out; the budgeted run spends a
frozen timing table, so its Adam steps do not depend on the machine.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

REFERENCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "loop_reference.json")
TINY = ["--samples", "4", "--adam-steps", "3", "--mpc-steps", "2"]
STEP_FIELDS = ("omega", "bucket", "adam_steps", "objective", "predicted_objective", "distance", "inside", "action",
               "kind_inside", "mixing", "phase", "kind", "waypoint", "centres", "astar_steps")
TIMING = dict(device="reference", samples=4, horizon=1, fixed_s={"16": 0.01, "32": 0.012, "64": 0.015, "100": 0.02},
              step_s={"16": 0.004, "32": 0.005, "64": 0.008, "100": 0.011})


def _steps(metrics: dict) -> list[dict]:
    return [{k: r[k] for k in STEP_FIELDS if k in r} for r in metrics["steps"]]


def _summary(summary: dict) -> dict:
    """evaluate's summary without what depends on the machine or the checkout (device, seconds, the checkpoint's
    path in the dynamics' name)."""
    def strip(tree):
        if isinstance(tree, dict):
            return {k: strip(v) for k, v in tree.items() if k not in ("device", "seconds", "dynamics")}
        return tree

    return strip(json.loads(json.dumps(summary)))


def record(folder: str) -> dict:
    """Run every reference case with outputs under ``folder`` (gather, adaptive, letter, sort, evaluate, sensor);
    returns the reduced results."""
    from dynres_jax.commands import evaluate, gather, redistribute, sort
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, SHIPPED_REGRESSOR

    timing = os.path.join(folder, "frozen_timing.json")
    with open(timing, "w") as f:
        json.dump(TIMING, f)
    out = lambda name: os.path.join(folder, name)  # noqa: E731
    runs = {}
    runs["gather_fixed"] = _steps(gather.main([*TINY, "--pieces", "40", "--resolution", "25", "--seed", "3",
                                                "--out", out("gather")]))
    runs["gather_adaptive"] = _steps(gather.main([*TINY, "--pieces", "40", "--resolution", "adaptive", "--seed", "4",
                                                   "--time-budget", "0.03", "--timing", timing, "--regressor",
                                                   SHIPPED_REGRESSOR, "--ckpt", SHIPPED_DYNAMICS,
                                                   "--out", out("adaptive")]))
    runs["redistribute"] = _steps(redistribute.main([*TINY, "--pieces", "40", "--letter", "J", "--resolution", "25",
                                                      "--objective", "paper",  # as recorded (the hinge: test_objective)
                                                      "--seed", "5", "--out", out("letter")]))
    runs["sort"] = _steps(sort.main([*TINY, "--pieces", "20", "20", "--seed", "6", "--out", out("sort")]))
    summary = evaluate.main(["--quick", "--episodes", "2", "--mpc-steps", "2", "--pieces", "40", "--samples", "4",
                             "--adam-steps", "3", "--methods", "25", "adaptive", "oracle", "--seed", "7",
                             "--workers", "1", "--out", out("evaluate")])
    runs["evaluate"] = _summary(summary)
    with open(out("evaluate/oracle.json")) as f:
        oracle = json.load(f)
    runs["evaluate_oracle"] = {k: oracle[k] for k in ("final_distance", "final_inside", "omega", "adam_steps",
                                                       "final_pieces")}
    sensed = evaluate.main(["--quick", "--episodes", "2", "--mpc-steps", "2", "--pieces", "40", "--samples", "4",
                            "--adam-steps", "3", "--methods", "20", "--sensor", "realsense", "--seed", "8",
                            "--workers", "1", "--out", out("sensor")])
    runs["evaluate_sensor"] = _summary(sensed)
    return json.loads(json.dumps(runs))


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        result = record(tmp)
    os.makedirs(os.path.dirname(REFERENCE), exist_ok=True)
    with open(REFERENCE, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {REFERENCE}", file=sys.stderr)
