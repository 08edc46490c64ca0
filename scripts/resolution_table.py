"""Issue 37's tables from its GPU runs: Fig. 5 (every fixed ω against adaptive ω, paired), the oracle's gain split into
choosing among plans (best of K at ω = 50) and choosing ω, and the label reliability and Fig. 4 of tradeoff.

    python scripts/resolution_table.py --fig5 FIG5_OUT --split gather=SPLIT_G redistribute=SPLIT_R \
        --labels REL_OUT --out docs/resolution

FIG5_OUT: the fig5 recipe's folder (TASK_budget, TASK_budget_gnew, gather_nobudget); SPLIT_*: evaluate runs of
50, best5 and oracle; REL_OUT: the reliability recipe's folder (reliability/, fig4/, labels_2). Episode i is the
same pile, goal and planner keys in every run of a task, so runs pair across folders. Writes OUT/resolution.json and
OUT/resolution.md.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ladder_table import _pair  # noqa: E402

from dynres_jax.control.tasks import succeeded  # noqa: E402
from dynres_jax.io import files  # noqa: E402
from dynres_jax.stats import wilson  # noqa: E402

FIXED = ("10", "25", "50", "75", "100")


def method(folder: str, name: str) -> dict:
    """A method's run as ladder_table reads one (episode, success, distance per episode), with its mean ω and Adam
    steps and its device."""
    with open(os.path.join(folder, f"{name}.json")) as f:
        run = json.load(f)
    return dict(episode=list(range(len(run["final_inside"]))), success=succeeded(run["final_inside"]),
                distance=np.asarray(run["final_distance"]), adam_steps=float(np.mean(run["adam_steps"])),
                omega=float(np.mean(run["omega"])), device=run["device"])


def row(name: str, m: dict) -> dict:
    k, n = int(m["success"].sum()), len(m["success"])
    return dict(method=name, final_d=float(m["distance"].mean()), success=k / n, success_ci95=wilson(k, n),
                adam_steps=m["adam_steps"], omega=m["omega"], episodes=n)


def fig5(folder: str, name: str, methods, extra: dict) -> dict:
    """One task's fixed ω and adaptive (folder/name), and extra choosers run on the same episodes in other folders:
    {label: (folder, method)}; each chooser against the best fixed ω."""
    runs = {m: method(os.path.join(folder, name), m) for m in methods}
    runs.update({label: method(path, m) for label, (path, m) in extra.items() if os.path.isdir(path)})
    fixed = [m for m in FIXED if m in runs]
    best = min(fixed, key=lambda m: runs[m]["distance"].mean())
    return dict(rows=[row(m, r) for m, r in runs.items()], best_fixed=best, device=runs[best]["device"],
                against_best={m: _pair(runs[m], runs[best]) for m in runs if m not in fixed})


def split(folder: str, omega: str = "50") -> dict:
    """The oracle's gap over ω (the best-of-5 run's --best-omega), the part the best of 5 plans at ω buys, and the
    rest: the part that is ω."""
    runs = {m: method(folder, m) for m in (omega, "best5", "oracle")}
    gap, plans = (runs[omega]["distance"] - runs[m]["distance"] for m in ("oracle", "best5"))
    return dict(rows=[row(m, r) for m, r in runs.items()], oracle_gap=float(gap.mean()),
                plan_selection=float(plans.mean()), omega_part=float((gap - plans).mean()),
                oracle_vs_best5=_pair(runs["oracle"], runs["best5"]))


def fmt(p: dict) -> str:
    d, s = p["delta_d"], p["success"]
    return (f"{d['mean']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}]; successes only here {s['first_only']}, "
            f"only there {s['second_only']} (p = {s['p']:.2f})")


def table(rows) -> list[str]:
    out = ["| method | final d (px) | success | Wilson 95 % | mean ω | mean Adam steps |",
           "|---|---:|---:|---|---:|---:|"]
    return out + [f"| {r['method']} | {r['final_d']:.3f} | {r['success']:.0%} | {r['success_ci95'][0]:.0%}-"
                  f"{r['success_ci95'][1]:.0%} | {r['omega']:.1f} | {r['adam_steps']:.1f} |" for r in rows]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fig5", required=True)
    parser.add_argument("--split", nargs="+", required=True, metavar="TASK=DIR")
    parser.add_argument("--labels", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    result = {}
    for task in ("gather", "redistribute"):
        result[f"fig5 {task}"] = fig5(args.fig5, f"{task}_budget", (*FIXED, "adaptive"), {
            "adaptive, g on new labels": (os.path.join(args.fig5, f"{task}_budget_gnew"), "adaptive"),
            "probe (no labels)": (os.path.join(args.fig5, f"{task}_budget_probe"), "probe")})
    for task in ("gather", "redistribute"):
        result[f"fig5 {task}, no budget"] = fig5(args.fig5, f"{task}_nobudget", ("25", "50", "100", "adaptive"), {})
    result.update({f"split {task}": split(folder) for task, folder in (s.split("=", 1) for s in args.split)})
    with open(os.path.join(args.labels, "reliability", "reliability.json")) as f:
        reliability = json.load(f)
    result["reliability"] = {k: v for k, v in reliability.items() if not isinstance(v, list)}
    result["fig4"] = {}
    for run in ("fig4", "fig4_2"):
        path = os.path.join(args.labels, run, "tradeoff.json")
        if os.path.exists(path):
            with open(path) as f:
                result["fig4"][run] = {k: v for k, v in json.load(f).items() if k != "scenes"}
    lines = []
    for key, entry in result.items():
        if key.startswith("fig5"):
            lines += [f"## Fig. 5, {key[5:]} (best fixed ω: {entry['best_fixed']}; {entry['device']})", "",
                      *table(entry["rows"]), ""]
            lines += [f"- {m} - ω = {entry['best_fixed']}: Δd {fmt(p)}" for m, p in entry["against_best"].items()]
            lines.append("")
        elif key.startswith("split"):
            lines += [f"## The oracle's gap, {key[6:]}", "", *table(entry["rows"]), "",
                      f"- gap over ω = 50: {entry['oracle_gap']:.3f} px; the best of 5 plans at ω = 50 buys "
                      f"{entry['plan_selection']:.3f}; the part that is ω: {entry['omega_part']:+.3f} px",
                      f"- oracle - best5: Δd {fmt(entry['oracle_vs_best5'])}", ""]
    files.write_json(os.path.join(args.out, "resolution.json"), result)
    files.write_text(os.path.join(args.out, "resolution.md"), "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
