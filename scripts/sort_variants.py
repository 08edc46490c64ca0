"""Sort's policy variants compared episode by episode, from the folders ``scripts/gpu_sort_evaluate.sh`` wrote: per
pair and variant the success share (``tasks.sort_succeeded``) with its Wilson interval, why each failure failed, and
each variant against the first (paired: successes only here / only there with McNemar's p, final d's mean difference
with its bootstrap interval).

    python scripts/sort_variants.py --runs RUNS/sort_evaluate --variants base mix10 --out docs/sort/mixing/fresh.md

RUNS holds VARIANT/sort-A-B/METHOD.json (``--method``, default 50). A failure is "mixing" when both kinds are at
least 80 % inside their goals but 5 % or more of the pieces lie in the other kind's goal, "short" when a kind is below
80 % with mixing under 5 %, "both" otherwise. Writes the Markdown table to --out and prints it.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from dynres_jax.control.tasks import SORT_INSIDE, SORT_MIXING, sort_succeeded
from dynres_jax.io import files
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson

PAIRS = ("coffee-candy", "almond-mnm", "rice-granola")


def failures(result: dict) -> dict:
    """A method's results -> counts of its failures by cause (mixing, short, both)."""
    inside = np.asarray(result["final_kind_inside"]).min(axis=1) >= SORT_INSIDE - 1e-6
    mixed = np.asarray(result["final_mixing"]) >= SORT_MIXING
    failed = ~sort_succeeded(result["final_kind_inside"], result["final_mixing"])
    return dict(mixing=int(np.sum(failed & inside & mixed)), short=int(np.sum(failed & ~inside & ~mixed)),
                both=int(np.sum(failed & ~inside & mixed)))


def table(runs: str, variants: list[str], method: str) -> str:
    """The Markdown table of every pair (rows) and variant."""
    lines = ["| pair | variant | success (95 % CI) | failures: mixing / short / both | final mixing | "
             f"against {variants[0]}: only here / only there (McNemar p) | Δ final d (95 % CI) |",
             "|---|---|---:|---:|---:|---:|---:|"]
    totals = {v: [0, 0] for v in variants}
    for pair in PAIRS:
        results = {}
        for v in variants:
            path = os.path.join(runs, v, f"sort-{pair}", f"{method}.json")
            if os.path.exists(path):
                with open(path) as f:
                    results[v] = json.load(f)
        if variants[0] not in results:
            continue
        first = results[variants[0]]
        for v, r in results.items():
            ok = sort_succeeded(r["final_kind_inside"], r["final_mixing"])
            totals[v][0] += int(ok.sum())
            totals[v][1] += len(ok)
            lo, hi = wilson(int(ok.sum()), len(ok))
            cause = failures(r)
            row = (f"| {pair} | {v} | {ok.mean():.0%} ({lo:.0%}-{hi:.0%}), {ok.sum()} of {len(ok)} | "
                   f"{cause['mixing']} / {cause['short']} / {cause['both']} | {np.mean(r['final_mixing']):.1%} |")
            if v == variants[0]:
                lines.append(row + " | |")
                continue
            base = sort_succeeded(first["final_kind_inside"], first["final_mixing"])
            test = mcnemar(ok, base)
            delta = paired_bootstrap(r["final_distance"], first["final_distance"])
            p = "p < 0.001" if test["p"] < 0.001 else f"p = {test['p']:.3f}"
            lines.append(row + f" {test['first_only']} / {test['second_only']} ({p}) | "
                               f"{delta['mean']:+.2f} [{delta['ci95'][0]:+.2f}, {delta['ci95'][1]:+.2f}] |")
    for v, (k, n) in totals.items():
        if n:
            lo, hi = wilson(k, n)
            lines.append(f"| all pairs | {v} | {k / n:.0%} ({lo:.0%}-{hi:.0%}), {k} of {n} | | | | |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", required=True, help="the sort_evaluate folder of gpu_sort_evaluate.sh")
    parser.add_argument("--variants", nargs="+", required=True, help="variant folders; the first is the reference")
    parser.add_argument("--method", default="50")
    parser.add_argument("--out", default=None, help="write the table here (Markdown)")
    args = parser.parse_args(argv)
    text = table(args.runs, args.variants, args.method)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        files.write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
