"""Issue 35's ladder table from the folders the ladder recipe wrote (unpacked lanes): per task and kind, each
method's success and final d, the paired comparisons that split the oracle's gain (oracle against best-of-K) and the
model's failures (which rung first succeeds where ω = 50 fails), and a plot.

    python scripts/ladder_table.py --runs RUNS --out docs/ladder

RUNS holds ``*/TASK-KIND-COUNT/METHOD.json`` (evaluate) and ``*/sort-A-B-METHOD/SEED/metrics.json`` (sort); a folder
found twice (a lane packed by several calls) is read once. Writes OUT/ladder.json (per method and episode: success,
final d, inside share; the summaries and comparisons), OUT/ladder.md (the tables) and OUT/ladder.png.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re

import numpy as np

from dynres_jax.control.tasks import sort_succeeded, succeeded
from dynres_jax.io import files
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson

ORDER = ("50", "sim", "rerank", "best5", "oracle")  # the rungs, cheapest first


def _method(method: str, model: str | None) -> str:
    """A run's name: its method, with "@MODEL" where the ladder's job named a checkpoint (folder suffix -MODEL;
    the shipped one's folder, dynres_jax/checkpoints/dynamics, gives "checkpoints": "shipped")."""
    return method if model is None else f"{method}@{'shipped' if model == 'checkpoints' else model}"


def evaluate_runs(root: str) -> dict:
    """{(task, kind): {method: {episode [E] (indices), success [E], distance [E], inside [E], seconds, device}}};
    a job that named a checkpoint gives method "METHOD@MODEL" (``_method``)."""
    runs = {}
    for path in sorted(glob.glob(os.path.join(root, "**", "*.json"), recursive=True)):
        folder, method = os.path.basename(os.path.dirname(path)), os.path.basename(path)[:-5]
        match = re.fullmatch(r"(gather|redistribute)-([a-z]+)-(\d+)(?:-([a-z0-9]+))?", folder)
        if not match or method in ("run", "summary"):
            continue
        with open(path) as f:
            r = json.load(f)
        runs.setdefault(match.group(1, 2), {})[_method(method, match.group(4))] = dict(
            episode=list(range(len(r["final_inside"]))), success=succeeded(r["final_inside"]).tolist(),
            distance=r["final_distance"], inside=r["final_inside"],
            seconds=r["seconds"], device=r["device"])
    return runs


def sort_runs(root: str) -> dict:
    """{("sort", "A-B"): {method ("50": --method model at ω = 50): {episode [E] (seeds), success [E], distance [E]
    (1 - the lower kind's inside share), inside [E] (both kinds' mean), mixing [E], seconds}}}, seeds in order."""
    found = {}
    for path in glob.glob(os.path.join(root, "**", "metrics.json"), recursive=True):
        folder = os.path.basename(os.path.dirname(os.path.dirname(path)))
        match = re.fullmatch(r"sort-([a-z]+-[a-z]+)-([a-z0-9]+)(?:-([a-z0-9]+))?", folder)
        if match:
            method = _method("50" if match.group(2) == "model" else match.group(2),  # sort's model plans at ω = 50
                             match.group(3))
            found.setdefault((match.group(1), method), {})[int(os.path.basename(os.path.dirname(path)))] = path
    runs = {}
    for (pair, method), paths in sorted(found.items()):
        rows = []
        for seed in sorted(paths):
            with open(paths[seed]) as f:
                m = json.load(f)
            inside, mixing = m["final_inside"], m["final_mixing"]
            rows.append((seed, sort_succeeded(inside, mixing), 1 - min(inside),
                         float(np.mean(inside)), mixing, m["seconds"]))
        seed, success, distance, inside, mixing, seconds = zip(*rows, strict=True)
        runs.setdefault(("sort", pair), {})[method] = dict(episode=list(seed), success=list(success),
                                                          distance=list(distance), inside=list(inside),
                                                          mixing=list(mixing), seconds=float(np.sum(seconds)))
    return runs


def _common(*runs) -> tuple[list[int], list[dict]]:
    """The episodes every run ran (in order), and each run's values on them: {success, distance} arrays."""
    common = sorted(set.intersection(*(set(r["episode"]) for r in runs)))
    at = [{e: i for i, e in enumerate(r["episode"])} for r in runs]
    return common, [dict(success=np.array([r["success"][a[e]] for e in common], bool),
                         distance=np.array([r["distance"][a[e]] for e in common]))
                    for r, a in zip(runs, at, strict=True)]


def _pair(first: dict, second: dict) -> dict:
    """first against second on their common episodes: Δ final d (first - second) with a paired-bootstrap 95 %
    interval, and McNemar's test on success."""
    common, (a, b) = _common(first, second)
    return dict(episodes=len(common), delta_d=paired_bootstrap(a["distance"], b["distance"]),
                success=mcnemar(a["success"], b["success"]))


def compare(runs: dict, base: str) -> dict:
    """Each method against ``base`` on their common episodes (``_pair``); the oracle against best-of-K (the oracle's
    gain split); and, of the episodes every method ran where base fails, how many each rung rescues ("rescued_by")
    and how many none does."""
    out = {m: _pair(r, runs[base]) for m, r in runs.items() if m != base
           and len(set(r["episode"]) & set(runs[base]["episode"])) >= 2}
    best = next((m for m in runs if re.fullmatch(r"best\d+", m)), None)
    if "oracle" in runs and best:  # choosing ω on top of choosing among as many plans
        out["oracle_vs_best"] = dict(best=best, **_pair(runs["oracle"], runs[best]))
    others = [m for m in runs if m != base]
    common, values = _common(runs[base], *(runs[m] for m in others))
    fails = ~values[0]["success"]
    rescued = {m: int(np.sum(fails & v["success"])) for m, v in zip(others, values[1:], strict=True)}
    anyone = np.any([v["success"] for v in values[1:]], axis=0) if others else np.zeros(len(common), bool)
    return dict(methods=out, split=dict(episodes=len(common), base_fails=int(fails.sum()), rescued_by=rescued,
                                        rescued_by_none=int(np.sum(fails & ~anyone))))


def table(name: str, runs: dict, comparison: dict) -> list[str]:
    base = next(m for m in ORDER if m in runs)
    lines = [f"### {name}", "", "| method | episodes | success (95 % CI) | final d | Δd against "
             f"{base} (paired 95 % CI) | successes only here / only in {base} (McNemar p) | seconds |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for method in sorted(runs, key=lambda m: ORDER.index(m) if m in ORDER else len(ORDER)):
        r, c = runs[method], comparison["methods"].get(method)
        k, n = int(np.sum(r["success"])), len(r["success"])
        lo, hi = wilson(k, n)
        delta = (f"{c['delta_d']['mean']:+.2f} [{c['delta_d']['ci95'][0]:+.2f}, {c['delta_d']['ci95'][1]:+.2f}]"
                 f" on {c['episodes']}" if c else "")
        mc = f"{c['success']['first_only']} / {c['success']['second_only']} (p = {c['success']['p']:.3f})" if c else ""
        lines.append(f"| {method} | {n} | {k / n:.0%} ({lo:.0%}-{hi:.0%}) | {np.mean(r['distance']):.2f} | {delta} | "
                     f"{mc} | {r['seconds']:.0f} |")
    s = comparison["split"]
    if "oracle_vs_best" in comparison["methods"]:
        o = comparison["methods"]["oracle_vs_best"]
        lines += ["", f"Oracle against {o['best']} on {o['episodes']} episodes: Δd {o['delta_d']['mean']:+.2f} "
                  f"[{o['delta_d']['ci95'][0]:+.2f}, {o['delta_d']['ci95'][1]:+.2f}], successes only with the oracle "
                  f"{o['success']['first_only']}, only with {o['best']} {o['success']['second_only']} "
                  f"(McNemar p = {o['success']['p']:.3f})."]
    if name.startswith("sort"):
        lines += ["", "Sort's target: both kinds ≥ 80 % inside their own goal and mixing below 5 %; its final d here "
                  "is 1 - the lower kind's inside share."]
    rescued = ", ".join(f"{m} {k}" for m, k in s["rescued_by"].items())
    lines += ["", f"Of the {s['episodes']} episodes every method ran, {base} fails {s['base_fails']}; "
              f"rescued (succeeds where {base} fails) by {rescued}; by none: {s['rescued_by_none']}.", ""]
    return lines


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = list(results)
    methods = [m for m in ORDER if any(m in results[k]["runs"] for k in names)]
    width = 0.8 / len(methods)
    for j, method in enumerate(methods):
        for i, name in enumerate(names):
            r = results[name]["runs"].get(method)
            if r is None:
                continue
            k, n = int(np.sum(r["success"])), len(r["success"])
            lo, hi = wilson(k, n)
            x = i + (j - (len(methods) - 1) / 2) * width
            ax.bar(x, k / n, width, color=f"C{j}", label=method if i == names.index(
                next(nm for nm in names if method in results[nm]["runs"])) else None)
            ax.errorbar(x, k / n, [[max(k / n - lo, 0)], [max(hi - k / n, 0)]], color="k", lw=0.8, capsize=2)
            ax.text(x, 0.02, str(n), ha="center", fontsize=6, color="w")
    ax.set_xticks(range(len(names)), names, fontsize=8)
    ax.set(ylabel="episodes meeting the target", ylim=(0, 1.05), title="the ladder: which rung succeeds")
    ax.legend(fontsize=7, ncol=len(methods))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", required=True, help="the unpacked lanes of the ladder recipe")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    found = {**evaluate_runs(args.runs), **sort_runs(args.runs)}
    if not found:
        parser.error(f"--runs {args.runs!r} holds no ladder run (TASK-KIND-COUNT/METHOD.json, sort-A-B-METHOD/SEED/)")
    results, lines = {}, ["# The ladder", ""]
    for (task, kind), runs in found.items():
        base = next(m for m in ORDER if m in runs)
        results[f"{task} {kind}"] = dict(runs=runs, comparison=compare(runs, base))
        lines += table(f"{task}, {kind}", runs, results[f"{task} {kind}"]["comparison"])
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "ladder.json"), results)
    files.atomic_write(os.path.join(args.out, "ladder.md"), lambda f: f.write("\n".join(lines).encode()))
    plot(results, os.path.join(args.out, "ladder.png"))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
