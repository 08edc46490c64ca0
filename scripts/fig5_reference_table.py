"""Issue 51 item 3's table from the fig5_reference recipe's folder: for each stage (TASK_BUDGETs), every method's
row, each against the best fixed ω (paired), the oracle's gain split into choosing among plans (best of 5 at the run's
--best-omega) and choosing ω (oracle - best5), and where adaptive ran, the share of that ω part it recovers: its gain
over the best fixed ω over the ω part (both paired means).

    python scripts/fig5_reference_table.py RUN_DIR --out docs/reference_planner/fig5

Writes OUT/fig5.json and OUT/fig5.md; copies each stage's summary, run settings and timing table to OUT/STAGE/.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from resolution_table import FIXED, fig5, fmt, split, table  # noqa: E402

from dynres_jax.io import files  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="the fig5_reference recipe's OUT")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    stages = sorted(d for d in os.listdir(args.run) if os.path.exists(os.path.join(args.run, d, "summary.json")))
    if not stages:
        parser.error(f"{args.run} holds no finished stage (TASK_BUDGETs/summary.json)")
    result, lines = {}, []
    for stage in stages:
        folder = os.path.join(args.run, stage)
        methods = [m for m in ("oracle", "best5", "adaptive", *FIXED)
                   if os.path.exists(os.path.join(folder, f"{m}.json"))]
        with open(os.path.join(folder, "run.json")) as f:
            omega = str(json.load(f)["config"]["best_omega"])
        entry = fig5(args.run, stage, methods, {})
        entry["split"] = s = split(folder, omega)
        lines += [f"## {stage} (best fixed ω: {entry['best_fixed']}; {entry['device']})", "", *table(entry["rows"]), "",
                  *(f"- {m} - ω = {entry['best_fixed']}: Δd {fmt(p)}" for m, p in entry["against_best"].items()),
                  f"- oracle's gap over ω = {omega}: {s['oracle_gap']:.3f} px; the best of 5 plans at ω = {omega} buys "
                  f"{s['plan_selection']:.3f}; the part that is ω: {s['omega_part']:+.3f} px",
                  f"- oracle - best5: Δd {fmt(s['oracle_vs_best5'])}"]
        if "adaptive" in entry["against_best"]:
            entry["adaptive_share"] = -entry["against_best"]["adaptive"]["delta_d"]["mean"] / s["omega_part"]
            lines.append(f"- adaptive recovers {entry['adaptive_share']:+.0%} of the ω part")
        result[stage] = entry
        lines.append("")
        os.makedirs(os.path.join(args.out, stage), exist_ok=True)
        for name in ("summary.json", "run.json", "timing.json"):
            shutil.copy(os.path.join(folder, name), os.path.join(args.out, stage, name))
    files.write_json(os.path.join(args.out, "fig5.json"), result)
    files.write_text(os.path.join(args.out, "fig5.md"), "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
