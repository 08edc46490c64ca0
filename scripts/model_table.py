"""Dynamics models compared in closed loop (issue 36): every model's ladder runs against a base model on the
episodes both ran (episode i is the same pile, goal and planner keys in every run), per task and kind: success with
its Wilson interval, final d, the paired Δd (bootstrap 95 % interval) and McNemar's test on success.

    python scripts/model_table.py --runs UNPACKED_LANES... --base 50@shipped --out docs/model_at_scale
    python scripts/model_table.py --runs ... --ladder docs/ladder/ladder.json   # the ladder's ω = 50 rows as "50"

Writes OUT/closed_loop.md and closed_loop.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ladder_table import _pair, evaluate_runs, sort_runs  # noqa: E402

from dynres_jax.io import files  # noqa: E402
from dynres_jax.stats import wilson  # noqa: E402


def load(roots, ladder: str | None) -> dict:
    """{(task, kind): {name: run}} of every root (``evaluate_runs`` and ``sort_runs``), with the ladder file's ω = 50
    runs (the shipped model when the ladder ran) added as "50"."""
    runs = {}
    for root in roots:
        for found in (evaluate_runs(root), sort_runs(root)):
            for key, methods in found.items():
                runs.setdefault(key, {}).update(methods)
    if ladder:
        with open(ladder) as f:
            for name, entry in json.load(f).items():
                if "50" in entry["runs"]:
                    runs.setdefault(tuple(name.split(" ")), {}).setdefault("50", entry["runs"]["50"])
    return runs


def compare(runs: dict, base: str) -> dict:
    """{(task, kind): {name: summary, and against base on their common episodes}}; a task without base is skipped."""
    out = {}
    for key, models in sorted(runs.items()):
        if base not in models:
            continue
        rows = {}
        for name, r in sorted(models.items()):
            k, n = int(np.sum(r["success"])), len(r["success"])
            rows[name] = dict(episodes=n, success=k / n, ci95=wilson(k, n), final_d=float(np.mean(r["distance"])))
            if name != base and len(set(r["episode"]) & set(models[base]["episode"])) >= 2:
                rows[name]["against_base"] = _pair(r, models[base])
        out[" ".join(key)] = rows
    return out


def table(results: dict, base: str) -> str:
    lines = [f"| task | model | episodes | success (95 % CI) | final d | Δd against {base} (paired, 95 % CI) | "
             f"successes only this / only {base} (McNemar p) |", "|---|---|---:|---:|---:|---:|---:|"]
    for task, rows in results.items():
        for name, r in rows.items():
            pair = r.get("against_base")
            delta = (f"{pair['delta_d']['mean']:+.2f} [{pair['delta_d']['ci95'][0]:+.2f}, "
                     f"{pair['delta_d']['ci95'][1]:+.2f}] ({pair['episodes']})") if pair else ""
            split = (f"{pair['success']['first_only']} / {pair['success']['second_only']} "
                     f"(p = {pair['success']['p']:.3f})") if pair else ""
            lines.append(f"| {task} | {name} | {r['episodes']} | {100 * r['success']:.0f} % "
                         f"({100 * r['ci95'][0]:.0f}-{100 * r['ci95'][1]:.0f}) | {r['final_d']:.2f} | {delta} | "
                         f"{split} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", required=True, help="folders holding unpacked lanes")
    parser.add_argument("--base", default="50@shipped", help="the run every other is compared with")
    parser.add_argument("--ladder", default=None, help="a ladder.json whose ω = 50 runs join as '50'")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    results = compare(load(args.runs, args.ladder), args.base)
    if not results:
        parser.error(f"no task has a run named {args.base!r}")
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "closed_loop.json"), results)
    text = table(results, args.base)
    files.write_text(os.path.join(args.out, "closed_loop.md"), text + "\n")
    print(text)
    return results


if __name__ == "__main__":
    main()
