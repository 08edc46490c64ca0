"""scripts/ab_planner.py times each code version in its own process against that version's own package."""

import json
import math
import os
import shutil
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_each_version_is_timed_on_its_own_package(tmp_path):
    log, folder = tmp_path / "ab.jsonl", tmp_path / "copy"
    for part in ("dynres_jax", "experiments", os.path.join("checkpoints", "dynamics")):
        shutil.copytree(os.path.join(REPO, part), folder / part)
    out = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "ab_planner.py"), "HEAD", "WORKTREE",
                          str(folder), "--quick", "--rounds", "1", "--json", str(log)], capture_output=True, text=True,
                         cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]
    runs = {r["version"]: r for r in map(json.loads, log.read_text().splitlines())}
    assert set(runs) == {"HEAD", "WORKTREE", str(folder)}
    # HEAD ran from the extracted revision, WORKTREE from the repository, the folder from itself: none imported
    # another's package.
    assert runs["WORKTREE"]["code"] == os.path.join(REPO, "dynres_jax", "__init__.py")
    assert runs[str(folder)]["code"] == str(folder / "dynres_jax" / "__init__.py")
    assert not runs["HEAD"]["code"].startswith(REPO + os.sep) and runs["HEAD"]["code"].endswith(
        os.path.join("HEAD", "dynres_jax", "__init__.py"))
    for run in runs.values():  # the benchmark's float32 row at its quick sizes
        assert run["edge_dtype"] == "float32" and run["params"] == 38403 and math.isfinite(run["ms_per_step"])
        assert run["plan_s"] > 0 and run["steps"] > run["short_steps"]
    assert "HEAD: " in out.stdout and "WORKTREE: " in out.stdout  # the summary lines


def test_a_folder_without_a_tree_is_refused_by_name(tmp_path):
    (tmp_path / "dynres_jax").mkdir()
    out = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "ab_planner.py"), str(tmp_path), "--quick"],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode != 0
    assert f"the folder {tmp_path} lacks experiments, checkpoints/dynamics" in out.stderr
