"""The README is a guide that works: its Python quick start runs as written, it stays short, its links resolve."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_the_quick_start_runs_as_written_and_the_push_helps(tmp_path):
    """The block under "Quick start in Python", run as a script from another folder: it plans with the shipped
    learned model and the push it executes lowers the distance d to the goal."""
    section = README.split("## Quick start in Python", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "quick_start.py").write_text(code)
    out = subprocess.run([sys.executable, "quick_start.py"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    m = re.search(r"^learned \(.*\): predicted c [\d.]+; d ([\d.]+) -> ([\d.]+) pixels$", out.stdout, re.M)
    assert m, out.stdout
    assert float(m.group(2)) < float(m.group(1))


def test_the_readme_is_a_short_guide_whose_links_resolve():
    assert len(README.splitlines()) <= 250
    for target in re.findall(r"\]\(([^)#]+)\)", README):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target
