"""The notebooks run top to bottom on a CPU in quick mode (DYNRES_QUICK=1), are stored without outputs, and draw.

Each notebook runs in a fresh Jupyter kernel in its own folder, as Jupyter runs it (the shipped checkpoints are package
data, so no path depends on the working directory); the kernel inherits this process's environment, quick mode
included.
"""

import glob
import os

import nbformat
import pytest
from nbclient import NotebookClient

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK_DIR = os.path.join(REPO_ROOT, "notebooks")
NOTEBOOKS = ["01_jit_planner.ipynb", "02_resolution_sweep.ipynb", "03_export_checkpoint.ipynb"]


def code_cells(nb):
    return [cell for cell in nb.cells if cell.cell_type == "code"]


def test_every_notebook_is_tested():
    found = sorted(os.path.basename(p) for p in glob.glob(os.path.join(NOTEBOOK_DIR, "*.ipynb")))
    assert found == sorted(NOTEBOOKS), "add new notebooks to NOTEBOOKS (or remove stale ones)"


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_without_outputs(name):
    nb = nbformat.read(os.path.join(NOTEBOOK_DIR, name), as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(code_cells(nb)):
        assert cell.outputs == [] and cell.execution_count is None, f"{name}: code cell {i} has stored outputs"


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_runs_in_quick_mode(name, monkeypatch):
    monkeypatch.setenv("DYNRES_QUICK", "1")
    nb = nbformat.read(os.path.join(NOTEBOOK_DIR, name), as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": NOTEBOOK_DIR}}).execute()

    cells = code_cells(nb)
    outputs = [out for cell in cells for out in cell.outputs]
    assert not [out for out in outputs if out.output_type == "error"], f"{name} raised"
    assert all(cell.execution_count is not None for cell in cells), f"{name}: not every code cell ran"
    first = "".join(out.get("text", "") for out in cells[0].outputs if out.output_type == "stream")
    assert "QUICK=True" in first, f"{name}: the kernel did not run in quick mode (first cell printed {first!r})"
    images = [out for out in outputs if out.output_type in ("display_data", "execute_result")
              and "image/png" in out.get("data", {})]
    assert images, f"{name} drew no figure (no image/png output)"
