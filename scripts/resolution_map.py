"""Issue 51 item 4: a map of where ω matters, from anytime surfaces (``tradeoff --surface``) of several planners and
sample counts, each priced by its own timing table.

    python scripts/resolution_map.py RUN [RUN ...] --out docs/resolution_map

RUN: a ``tradeoff --surface`` folder (surface.json and surface_K.npz: c*[ω, N, scene] and d before the push). At a
budget of B seconds a decision, ω affords the largest N of the surface's steps whose priced seconds fit B (none fits:
no push, c* = d before it). Per budget and run: the best fixed ω (lowest mean c* over all scenes of both kinds) and
its regret, the mean over scenes of c*(best fixed ω) - min over ω of c*(ω) (what choosing ω per scene could buy at
most), with a 95 % bootstrap interval over scenes. The per-scene minimum is taken over single plans (common random
numbers across ω), so the regret also counts plan noise: it bounds the ω effect from above. Writes map.json, map.md
and map.png (regret and best fixed ω against budget, one line per run).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from dynres_jax.control.budget import TimingTable
from dynres_jax.io import files

BUDGETS = tuple(float(b) for b in np.round(np.geomspace(0.03, 2.0, 10), 3))
RESAMPLES = 2000


def load(run: str) -> dict:
    """A surface run: its summary, c*[ω, N, S] and d0 [S] over every scene of both kinds, and with --repeats R > 1
    draws, c*[R, ω, N, S] of every plan draw."""
    with open(os.path.join(run, "surface.json")) as f:
        summary = json.load(f)
    raws = [np.load(os.path.join(run, f"surface_{k}.npz")) for k in range(len(summary["kinds"]))]
    out = dict(summary=summary, c_star=np.concatenate([r["c_star"] for r in raws], axis=-1),
               d0=np.concatenate([r["d0"] for r in raws]))
    if all("c_star_draws" in r for r in raws):
        out["draws"] = np.concatenate([r["c_star_draws"] for r in raws], axis=-1)
    return out


def priced(run: dict, budget: float, c: np.ndarray | None = None, timing: TimingTable | None = None) -> np.ndarray:
    """c*[..., ω, S] at ``budget`` seconds a decision: each ω at the most steps of the surface that fit (see above).
    c: [..., ω, N, S] (default: the run's c_star); timing: the table that prices a step (default: the run's own)."""
    s = run["summary"]
    c = run["c_star"] if c is None else c
    timing = TimingTable(**s["timing"]) if timing is None else timing
    out = np.empty(c.shape[:-2] + c.shape[-1:])
    for i, omega in enumerate(s["omegas"]):
        key = timing.key(omega, timing.buckets or s["buckets"])  # another device's table: priced at its buckets
        fits = [j for j, n in enumerate(s["steps"]) if timing.seconds(key, n) <= budget]
        out[..., i, :] = c[..., i, max(fits), :] if fits else run["d0"]
    return out


def regret(c: np.ndarray, rng: np.random.Generator) -> dict:
    """The best fixed ω's index and its regret against the per-scene best of c[ω, S], with a bootstrap interval over
    scenes (the best fixed ω chosen again in each resample)."""

    def one(cols):
        means = c[:, cols].mean(axis=1)
        best = int(np.argmin(means))
        return best, float(means[best] - c[:, cols].min(axis=0).mean())

    n = c.shape[1]
    best, value = one(np.arange(n))
    boot = [one(rng.integers(0, n, n))[1] for _ in range(RESAMPLES)]
    return dict(best=best, regret=value, ci95=[float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
                mean_c=c.mean(axis=1).tolist())


def name(run: dict, path: str) -> str:
    s = run["summary"]
    return f"{os.path.basename(os.path.normpath(path))} (M = {s['samples']}, {s['device']})"


def plot(result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 7), sharex=True)
    for label, rows in result.items():
        b = [r["budget"] for r in rows]
        (line,) = top.plot(b, [r["regret"] for r in rows], marker="o", ms=3, label=label)
        top.fill_between(b, *zip(*[r["ci95"] for r in rows], strict=True), color=line.get_color(), alpha=0.2)
        bottom.plot(b, [r["best_omega"] for r in rows], marker="o", ms=3, color=line.get_color())
    top.set(ylabel="regret of the best fixed ω (px)\n(what choosing ω per scene could buy)", xscale="log")
    top.axhline(0, color="grey", lw=0.5)
    top.legend(fontsize=7)
    bottom.set(xlabel="budget per decision (s, each run's own pricing)", ylabel="best fixed ω", xscale="log")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="tradeoff --surface folders")
    parser.add_argument("--out", required=True)
    parser.add_argument("--budgets", nargs="+", type=float, default=BUDGETS, help="seconds a decision")
    args = parser.parse_args(argv)
    for path in args.runs:
        if not os.path.exists(os.path.join(path, "surface.json")):
            parser.error(f"{path} holds no surface.json (made by python -m experiments.tradeoff --surface)")
    rng, result, lines = np.random.default_rng(0), {}, []
    for path in args.runs:
        run = load(path)
        omegas, label = run["summary"]["omegas"], name(run, path)
        rows = []
        for b in args.budgets:
            r = regret(priced(run, b), rng)
            rows.append(dict(budget=b, best_omega=omegas[r["best"]], regret=r["regret"], ci95=r["ci95"],
                             mean_c=dict(zip(map(str, omegas), r["mean_c"], strict=True))))
        result[label] = rows
        lines += [f"## {label}", "", "| budget (s) | best fixed ω | its mean c* (px) | regret (px) | 95 % |",
                  "|---:|---:|---:|---:|---|"]
        lines += [f"| {r['budget']:g} | {r['best_omega']} | {r['mean_c'][str(r['best_omega'])]:.3f} | "
                  f"{r['regret']:.3f} | {r['ci95'][0]:.3f}-{r['ci95'][1]:.3f} |" for r in rows]
        lines.append("")
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "map.json"), result)
    files.write_text(os.path.join(args.out, "map.md"), "\n".join(lines))
    plot(result, os.path.join(args.out, "map.png"))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
