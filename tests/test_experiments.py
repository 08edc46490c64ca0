"""Command-line entry points: each one's --help, and the simulator demo end to end on a tiny scene."""

import json
import subprocess
import sys

import pytest

from experiments import simulate


@pytest.mark.parametrize("module", ["simulate", "benchmark", "validate_physics", "gather", "redistribute", "sort",
                                    "plan", "generate_data", "train_dynamics", "eval_dynamics"])
def test_help(module):
    out = subprocess.run([sys.executable, "-m", f"experiments.{module}", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "usage" in out.stdout


def test_simulate_demo_writes_its_files(tmp_path):
    simulate.main(["--kind", "coffee", "candy", "--pieces", "3", "2", "--pushes", "1", "--resolution", "48",
                   "--layout", "two_blobs", "--out", str(tmp_path)])
    for name in ("pushes.gif", "final_rgb.png", "final_depth.png", "actions.json"):
        assert (tmp_path / name).stat().st_size > 0
    record = json.loads((tmp_path / "actions.json").read_text())
    assert len(record["actions"]) == 1 and record["broken"] is False
