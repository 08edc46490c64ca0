"""Issue 48 item 6: where Sort's episodes fail, read from each step's record (``SortPolicy``'s fields and scores).

    python scripts/sort_failures.py --runs RUNS --out docs/sort/trace.md

RUNS holds ``*/sort-A-B-METHOD[-MODEL]/SEED/metrics.json`` (the ladder recipe's folders, as
``scripts/ladder_table.py`` reads them). Per episode: success (both kinds >= 80 % inside their own goal, mixing below
5 %), the A* steps at the start and left at the end, the phases, how often the moved pile switched, and these flags
(true scores, not the perceived ones; an episode may raise several):

- stalled: 5 or more steps of the path phase spent moving a kind already >= 80 % inside its goal while the other
  kind is below 80 % (the pile that needs a push waits);
- unfinished: 3 or more A* steps left at the end (the piles did not get through their path in the MPC steps);
- mixing: both kinds >= 80 % inside, mixing >= 5 % (pieces left in the other kind's goal);
- short: none of these (a kind ends below 80 % with its path done).

Writes a markdown file: per run the counts of each flag among its failures, then the episodes.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re

from dynres_jax.control.tasks import SORT_INSIDE, sort_kinds_inside, sort_mixed, sort_succeeded
from dynres_jax.io import files

STALLED_STEPS, UNFINISHED_STEPS = 5, 3
FLAGS = ("stalled", "unfinished", "mixing", "short")


def _one(field):
    """A record's field: the loop stores arrays [B] with B = 1 as one-element lists."""
    return field[0] if isinstance(field, list) and len(field) == 1 else field


def trace(metrics: dict) -> dict:
    """One episode's summary from sort's metrics.json: success, flags (``FLAGS``; empty on success), astar (steps at
    the start, left at the end), phases {phase: steps}, switches (changes of the moved kind)."""
    steps = [{k: _one(v) for k, v in s.items()} for s in metrics["steps"]]
    inside, mixing = steps[-1]["kind_inside"], steps[-1]["mixing"]
    success = sort_succeeded(inside, mixing)
    stalled = sum(s["phase"] == "path" and s["kind"] >= 0 and s["kind_inside"][s["kind"]] >= SORT_INSIDE
                  and s["kind_inside"][1 - s["kind"]] < SORT_INSIDE for s in steps)
    left = steps[-1]["astar_steps"]
    flags = []
    if not success:
        flags += ["stalled"] * (stalled >= STALLED_STEPS) + ["unfinished"] * (left >= UNFINISHED_STEPS)
        flags += ["mixing"] * bool(sort_kinds_inside(inside) and sort_mixed(mixing))
        flags = flags or ["short"]
    return dict(success=success, flags=flags, astar=(steps[0]["astar_steps"], left), inside=inside, mixing=mixing,
                phases=dict(collections.Counter(s["phase"] for s in steps)),
                switches=sum(a["kind"] != b["kind"] for a, b in zip(steps, steps[1:], strict=False)))


def runs(root: str) -> dict:
    """{run folder name (sort-A-B-METHOD[-MODEL]): {seed: trace}}, a folder found twice read once."""
    found = {}
    for path in sorted(glob.glob(os.path.join(root, "**", "metrics.json"), recursive=True)):
        folder = os.path.basename(os.path.dirname(os.path.dirname(path)))
        if re.fullmatch(r"sort-[a-z]+-[a-z]+-[a-z0-9]+(?:-[a-z0-9]+)?", folder):
            with open(path) as f:
                found.setdefault(folder, {})[int(os.path.basename(os.path.dirname(path)))] = trace(json.load(f))
    return found


def table(found: dict) -> str:
    """Markdown: per run its failures' flags counted, then one row per episode."""
    lines = ["| run | episodes | failures | " + " | ".join(FLAGS) + " |", "|---|---:|---:|" + "---:|" * len(FLAGS)]
    for name, episodes in sorted(found.items()):
        failed = [t for t in episodes.values() if not t["success"]]
        count = collections.Counter(f for t in failed for f in t["flags"])
        lines.append(f"| {name} | {len(episodes)} | {len(failed)} | " + " | ".join(str(count[f]) for f in FLAGS) + " |")
    lines += ["", "| run | seed | success | flags | inside | mixing | A* steps, start -> end | phases | switches |",
              "|---|---:|---|---|---|---:|---|---|---:|"]
    for name, episodes in sorted(found.items()):
        for seed, t in sorted(episodes.items()):
            inside = " / ".join(f"{x:.0%}" for x in t["inside"])
            phases = ", ".join(f"{k} {v}" for k, v in t["phases"].items())
            lines.append(f"| {name} | {seed} | {'yes' if t['success'] else 'no'} | {', '.join(t['flags'])} | "
                         f"{inside} | {t['mixing']:.0%} | {t['astar'][0]} -> {t['astar'][1]} | {phases} | "
                         f"{t['switches']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", required=True, help="folder holding sort-A-B-METHOD[-MODEL]/SEED/metrics.json")
    parser.add_argument("--out", required=True, help="markdown file to write")
    args = parser.parse_args(argv)
    found = runs(args.runs)
    if not found:
        parser.error(f"--runs {args.runs!r} holds no Sort episode (sort-A-B-METHOD/SEED/metrics.json)")
    files.write_text(args.out, table(found))
    print(table(found).split("\n\n")[0])
    return found


if __name__ == "__main__":
    main()
