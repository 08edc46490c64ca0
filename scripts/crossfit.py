"""Issue 69 item 1: a cross-fitted oracle over ω, from anytime surfaces planned R times per scene
(``python -m experiments.tradeoff --surface --repeats R``; docs/resolution_map).

    python scripts/crossfit.py RUN [RUN ...] --out DIR [--timing TABLE.json] [--budgets 0.05 0.25 1]

The oracle of ``choosers.OracleOmega`` keeps the best outcome of one plan per ω, so it also selects a plan (a
winner's curse). Here ω is chosen apart from the plan it scores: per scene s, budget and held-out draw r, ω*_r(s) is
the ω whose other R - 1 plans left the lowest mean c*, and the score is draw r's c* at ω*_r(s), averaged over r (leave
one out). Against it, on the same scenes: one plan at the best fixed ω (chosen on the tuning scenes, the even scene
indices of each kind; every figure below on the odd ones), best-of-R plans at that ω (plan selection alone), and the
single-plan oracle (min over ω of one draw, as the open-loop map took it). The gap "fixed - cross-fitted" with a
95 % bootstrap interval over test scenes is what choosing ω per scene buys with the plan noise removed. Labels
repeat: Spearman of the ω* that disjoint halves of the draws choose, over test scenes. Rows for all scenes and for
each scene kind of the surface (the best fixed ω chosen again on that kind's tuning scenes). Each ω affords the most
of the surface's Adam steps its price fits (``resolution_map.priced``): the run's own table or ``--timing``'s (e.g.
the 2-core CPU's, docs/budget/timing_cpu.json). Writes crossfit.json and crossfit.md to DIR and prints the table.
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from resolution_map import load, name, priced

from dynres_jax.commands.tradeoff import SURFACE_SCENES, ranks
from dynres_jax.control.budget import TimingTable
from dynres_jax.io import files
from dynres_jax.stats import bootstrap_mean

BUDGETS = (0.03, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0)


def cross_fitted(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c [R, ω, S] -> (per scene the mean over held-out draws r of c[ω*_r, r] [S], ω*_r's index [R, S]), ω*_r the
    lowest mean of the other R - 1 draws (the first on ties)."""
    r = c.shape[0]
    if r < 2:
        raise ValueError(f"a cross-fitted choice needs at least 2 plan draws, got {r}")
    others = (c.sum(axis=0, keepdims=True) - c) / (r - 1)  # [R, ω, S]: the other draws' mean
    pick = np.argmin(others, axis=1)  # [R, S]
    scored = np.take_along_axis(c, pick[:, None], axis=1)[:, 0]  # [R, S]
    return scored.mean(axis=0), pick


def spearman(a, b) -> float:
    """Rank correlation of a and b [S] (ties given their mean rank); NaN where either is constant."""
    ra, rb = ranks(a), ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def compare(c: np.ndarray, tune: np.ndarray, omegas, rng: np.random.Generator) -> dict:
    """c [R, ω, S] at one budget, tune [S] the tuning scenes -> the best fixed ω (tuning) and, on the other scenes,
    each chooser's mean c* [px] with the paired gaps' bootstrap intervals and the labels' repeatability."""
    test = ~tune
    fixed = int(np.argmin(c[:, :, tune].mean(axis=(0, 2))))
    t = c[:, :, test]
    one_fixed = t[:, fixed].mean(axis=0)  # [S]: one plan at the fixed ω, its expectation over draws
    crossfit, pick = cross_fitted(t)
    best_of_r = t[:, fixed].min(axis=0)
    single_oracle = t.min(axis=1).mean(axis=0)
    half = c.shape[0] // 2
    a, b = (np.asarray(omegas)[np.argmin(t[d].mean(axis=0), axis=0)] for d in (slice(0, half), slice(half, None)))
    gap = bootstrap_mean(one_fixed - crossfit, rng)
    return dict(best_fixed=int(omegas[fixed]), scenes=int(test.sum()), fixed=float(one_fixed.mean()),
                crossfit=float(crossfit.mean()), gap=gap["mean"], gap_ci95=list(gap["ci95"]),
                best_of_r=float(best_of_r.mean()), single_oracle=float(single_oracle.mean()),
                moved=float(np.mean(pick != fixed)), label_spearman=spearman(a, b),
                chosen={int(w): float(np.mean(pick == i)) for i, w in enumerate(omegas)})


def tuning_scenes(run: dict) -> np.ndarray:
    """[S]: the even scene indices of each kind (the kinds' scenes follow each other in the run's order)."""
    per_kind = run["summary"]["scenes"]
    return np.tile(np.arange(per_kind) % 2 == 0, len(run["summary"]["kinds"]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="tradeoff --surface --repeats R folders (R >= 3)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--budgets", nargs="+", type=float, default=BUDGETS, help="seconds a decision")
    parser.add_argument("--timing", default=None, help="a timing table that prices the steps (default: each run's)")
    args = parser.parse_args(argv)
    runs = {}
    for path in args.runs:
        if not os.path.exists(os.path.join(path, "surface.json")):
            parser.error(f"{path} holds no surface.json (made by python -m experiments.tradeoff --surface)")
        run = load(path)
        if run.get("draws") is None or run["draws"].shape[0] < 3:
            parser.error(f"{path} was planned once per scene; the cross-fitted oracle needs --repeats 3 or more")
        runs[path] = run
    timing = TimingTable.load(args.timing) if args.timing else None
    rng, result, lines = np.random.default_rng(0), {}, []
    for path, run in runs.items():
        s = run["summary"]
        if timing is not None and (timing.samples, timing.horizon) != (s["samples"], 1):
            parser.error(f"--timing {args.timing} prices {timing.samples} samples x horizon {timing.horizon}; "
                         f"{path} planned {s['samples']} samples")
        label = name(run, path) + (f", priced by {timing.device}" if timing else "")
        tune, per_kind = tuning_scenes(run), s["scenes"]
        groups = {"all": slice(None)} | {SURFACE_SCENES[i]: slice(i * per_kind, (i + 1) * per_kind)
                                         for i in range(len(s["kinds"]))}  # surface_i.npz's order, not the JSON's
        rows = [dict(budget=b, scenes_of=g, **compare(c[:, :, cols], tune[cols], s["omegas"], rng))
                for b in args.budgets for c in [priced(run, b, run["draws"], timing)] for g, cols in groups.items()]
        result[label] = rows
        lines += [f"## {label}, R = {run['draws'].shape[0]} plans a scene, {rows[0]['scenes']} test scenes", "",
                  "| budget (s) | scenes | best fixed ω (tuning) | one plan at it | cross-fitted ω | "
                  "fixed - cross-fitted (95 %) | scenes moved off it | best of R at it | single-plan oracle | "
                  "labels repeat (Spearman) |",
                  "|---:|---|---:|---:|---:|---|---:|---:|---:|---:|"]
        lines += [f"| {r['budget']:g} | {r['scenes_of']} ({r['scenes']}) | {r['best_fixed']} | {r['fixed']:.3f} | "
                  f"{r['crossfit']:.3f} | {r['gap']:+.3f} [{r['gap_ci95'][0]:+.3f}, {r['gap_ci95'][1]:+.3f}] | "
                  f"{r['moved']:.0%} | {r['best_of_r']:.3f} | {r['single_oracle']:.3f} | {r['label_spearman']:.2f} |"
                  for r in rows]
        lines.append("")
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "crossfit.json"), result)
    files.write_text(os.path.join(args.out, "crossfit.md"), "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
