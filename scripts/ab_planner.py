"""A/B of the planner's float32 Adam step across code versions, on whatever device JAX sees.

    python scripts/ab_planner.py HEAD WORKTREE [REV or FOLDER ...] [--rounds 2] [--shipped] [--quick] [--json FILE]

Each version is a git revision (its dynres_jax, experiments and checkpoints/dynamics, extracted with ``git archive``),
WORKTREE (the files as they are now) or a folder holding those three (a copy of another tree: the GPU machine gets
the working tree with main's history only, so other branches travel as folders). Every run is a fresh process (XLA's
options and caches start clean) that imports that version's package and times it with this tree's
``experiments.bench_planner.plan_step``: the benchmark's float32 row, ms per Adam step from plans of the full and a
tenth of the steps over 50 pushes x 30 re-samplings of 100 particles, on the reference architecture (``--shipped``:
the version's shipped checkpoint). The versions take turns over ``--rounds`` rounds, so drift of the machine hits them
alike. One JSON line per run (with the file each run imported, as a check), then the median and range of each
version's ms per step.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(REPO, "experiments", "bench_planner.py")
WORKTREE = "WORKTREE"
PATHS = ("dynres_jax", "experiments", "checkpoints/dynamics")  # what a version needs to plan and load its model

# The child: the version's tree first on sys.path, this tree's benchmark loaded from its file, so the benchmark's
# own (lazy) imports of dynres_jax resolve to the version under test.
CHILD = """
import importlib.util, json, sys
tree, bench_file, quick, shipped = sys.argv[1], sys.argv[2], sys.argv[3] == "1", sys.argv[4] == "1"
sys.path.insert(0, tree)
spec = importlib.util.spec_from_file_location("bench_planner_under_test", bench_file)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
import dynres_jax
print(json.dumps(dict(bench.plan_step(quick, shipped), code=dynres_jax.__file__)))
"""


def extract(rev: str, into: str) -> str:
    """The version's files in a folder of ``into`` (WORKTREE: the repository itself; a folder: itself) -> its path."""
    if rev == WORKTREE:
        return REPO
    if os.path.isdir(rev):
        missing = [p for p in PATHS if not os.path.isdir(os.path.join(rev, p))]
        if missing:
            raise SystemExit(f"the folder {rev} lacks {', '.join(missing)}: a version's folder holds "
                             f"{', '.join(PATHS)}")
        return os.path.abspath(rev)
    archive = subprocess.run(["git", "-C", REPO, "archive", "--format=tar", rev, *PATHS], capture_output=True,
                             check=True).stdout
    tree = os.path.join(into, rev.replace("/", "_"))
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(tree, filter="data")
    return tree


def time_version(tree: str, quick: bool, shipped: bool) -> dict:
    """One fresh process timing the package in ``tree`` -> ``plan_step``'s section plus ``code``."""
    out = subprocess.run([sys.executable, "-c", CHILD, tree, BENCH, str(int(quick)), str(int(shipped))],
                         capture_output=True, text=True, cwd=tree)
    if out.returncode != 0:
        raise RuntimeError(f"timing the version in {tree} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    """Run the A/B; returns {version: [ms per step of each round]} (also printed)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("versions", nargs="+",
                        help=f"git revisions, folders, or {WORKTREE} for the files as they are now")
    parser.add_argument("--rounds", type=int, default=2, help="times each version is timed, taking turns")
    parser.add_argument("--shipped", action="store_true", help="time the shipped checkpoint's architecture")
    parser.add_argument("--quick", action="store_true", help="the benchmark's tiny sizes (checks the A/B runs)")
    parser.add_argument("--json", help="append one JSON line per run here")
    args = parser.parse_args(argv)
    if len(set(args.versions)) != len(args.versions):
        parser.error(f"versions must differ, got {args.versions}")
    times = {v: [] for v in args.versions}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {v: extract(v, tmp) for v in args.versions}
        for r in range(args.rounds):
            for version, tree in trees.items():
                run = dict(time_version(tree, args.quick, args.shipped), version=version, round=r)
                times[version].append(run["ms_per_step"])
                print(json.dumps(run), flush=True)
                if args.json:
                    with open(args.json, "a") as f:
                        f.write(json.dumps(run) + "\n")
    for version, ms in times.items():
        print(f"{version}: {np.median(ms):.3f} ms per step (median of {len(ms)}; {min(ms):.3f}-{max(ms):.3f})")
    return times


if __name__ == "__main__":
    main()
