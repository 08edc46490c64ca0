"""Collect the held-out evaluations of several dynamics runs into one table and one picture: each run's one-step
error as a share of the sweep heuristic's, per ω (a full-state run, ``--state pieces``, has one value), against the
issue's target of one half.

    python scripts/dynamics_study.py OUT RUN [RUN ...]      # RUN: a run folder of scripts/ship_dynamics.sh

RUN/eval/eval.json is read (RUN/timing.json for the flags, where present). Writes OUT/study.json, OUT/study.md and
OUT/study.png; a run is named by its folder, or by NAME=RUN.
"""

from __future__ import annotations

import json
import os
import sys

from dynres_jax.io import files

SHIPPED = "--residual --push-frame --world-edges --loss distance --bin-position"  # checkpoints/dynamics/CARD.md


def collect(specs: list[str]) -> list[dict]:
    """[NAME=]RUN folders -> [{name, flags, step, ratio: {ω: model / heuristic one-step}, model_mm, heuristic_mm}]."""
    rows = []
    for spec in specs:
        name, _, folder = spec.rpartition("=")
        folder = folder.rstrip("/")
        result = json.load(open(os.path.join(folder, "eval", "eval.json")))
        timing = os.path.join(folder, "timing.json")
        flags = json.load(open(timing)).get("flags", "") if os.path.exists(timing) else ""
        omegas = sorted(result["omegas"], key=lambda o: (not o.isdigit(), int(o) if o.isdigit() else 0))
        first = {o: (result["omegas"][o]["model"][0], result["omegas"][o]["sweep heuristic"][0]) for o in omegas}
        rows.append({"name": name or os.path.basename(folder), "flags": flags, "step": result["step"],
                     "model_mm": {o: m for o, (m, _) in first.items()},
                     "heuristic_mm": {o: h for o, (_, h) in first.items()},
                     "ratio": {o: m / h for o, (m, h) in first.items()}})
    return rows


def table(rows: list[dict]) -> str:
    """Markdown, a row per run; the shipped model's flags (SHIPPED) are written F."""
    lines = ["| run | steps | one-step error / sweep heuristic's, per ω | flags (F: the shipped model's) |",
             "|---|---:|---|---|"]
    for r in rows:
        ratios = ", ".join(f"{o}: {v:.2f}" for o, v in r["ratio"].items())
        lines.append(f"| {r['name']} | {r['step']} | {ratios} | `{r['flags'].replace(SHIPPED, 'F')}` |")
    return "\n".join(lines)


def plot(rows: list[dict], path: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 0.32 * len(rows) + 1.9))
    ax = fig.subplots()
    for y, r in enumerate(rows):
        values = list(r["ratio"].values())
        ax.plot([min(values), max(values)], [y, y], color="0.6", lw=1)
        for omega, v in r["ratio"].items():
            ax.plot(v, y, "s" if omega == "pieces" else "o", ms=4, color="C3" if omega == "pieces" else "C0")
    ax.axvline(0.5, color="k", ls="--", lw=1, label="target: half the heuristic")
    ax.axvline(1.0, color="0.4", ls=":", lw=1, label="the heuristic")
    ax.plot([], [], "o", ms=4, color="C0", label="particles, ω = 10-100")
    ax.plot([], [], "s", ms=4, color="C3", label="full state (every piece's centre)")
    ax.set(yticks=range(len(rows)), yticklabels=[f"{r['name']} ({r['step']:,} steps)" for r in rows],
           xlabel="one-step error / sweep heuristic's", xlim=(0.4, 1.1))
    ax.invert_yaxis()
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12 * 12 / (len(rows) + 3)), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        sys.exit(__doc__)
    out, rows = argv[0], collect(argv[1:])
    os.makedirs(out, exist_ok=True)
    files.write_json(os.path.join(out, "study.json"), rows)
    text = table(rows)
    files.write_text(os.path.join(out, "study.md"), text + "\n")
    plot(rows, os.path.join(out, "study.png"))
    print(text)


if __name__ == "__main__":
    main(sys.argv[1:])
