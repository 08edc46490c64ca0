"""Issue 51 item 2, from surfaces already measured: would a budget do better buying samples than Adam steps? For one
planner's ``tradeoff --surface`` runs at several sample counts M (the same scenes), each ω and each amount of work
M x N that two or more (M, N) pairs of the surfaces reach: the mean c* (px) of each pair and the paired difference
"most samples - most steps" over scenes, with a 95 % bootstrap interval. Negative: samples buy more.

    python scripts/samples_or_steps.py RUN_M20 RUN_M50 RUN_M200 --out docs/resolution_map/samples_or_steps.md

Work M x N is what a budget pays where a step's price grows with the samples (a CPU; a GPU batch is nearly free up
to its width, so there the comparison flatters steps).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from resolution_map import load  # noqa: E402

from dynres_jax.io import files  # noqa: E402
from dynres_jax.stats import bootstrap_mean  # noqa: E402

RESAMPLES = 2000


def pairs_by_work(runs: dict) -> dict:
    """{work M x N: [(M, index of N), ...] sorted by M} for the works that two or more pairs reach. runs: {M: run}."""
    by_work = {}
    for m, run in sorted(runs.items()):
        for j, n in enumerate(run["summary"]["steps"]):
            by_work.setdefault(m * n, []).append((m, j))
    return {w: p for w, p in sorted(by_work.items()) if len(p) > 1}


def compare(runs: dict, rng: np.random.Generator) -> list[dict]:
    """One row per (ω, work): each pair's mean c* and most samples - most steps with its bootstrap interval."""
    omegas = next(iter(runs.values()))["summary"]["omegas"]
    rows = []
    for work, pairs in pairs_by_work(runs).items():
        for i, omega in enumerate(omegas):
            c = [(m, runs[m]["summary"]["steps"][j], runs[m]["c_star"][i, j]) for m, j in pairs]  # c* [S] each
            diff = bootstrap_mean(c[-1][2] - c[0][2], rng, RESAMPLES)  # the most samples' pair - the most steps'
            rows.append(dict(omega=omega, work=work, means={f"{m}x{n}": float(v.mean()) for m, n, v in c},
                             samples_minus_steps=diff["mean"], ci95=list(diff["ci95"])))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="tradeoff --surface folders of one planner at different --samples")
    parser.add_argument("--out", required=True, help="a Markdown file")
    args = parser.parse_args(argv)
    for path in args.runs:
        if not os.path.exists(os.path.join(path, "surface.json")):
            parser.error(f"{path} holds no surface.json (made by python -m experiments.tradeoff --surface)")
    runs = {}
    for path in args.runs:
        run = load(path)
        runs[run["summary"]["samples"]] = run
    if len(runs) < 2:
        parser.error("give surfaces at two or more sample counts")
    rows = compare(runs, np.random.default_rng(0))
    lines = ["| ω | work M x N | mean c* of each M x N (px) | most samples - most steps (px) | 95 % |",
             "|---:|---:|---|---:|---|"]
    lines += [f"| {r['omega']} | {r['work']} | " + ", ".join(f"{k}: {v:.2f}" for k, v in r["means"].items())
              + f" | {r['samples_minus_steps']:+.2f} | {r['ci95'][0]:+.2f} to {r['ci95'][1]:+.2f} |" for r in rows]
    files.write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
