"""notebooks/quickstart.ipynb runs top to bottom (tiny settings) with a real Jupyter kernel."""

from __future__ import annotations

import json
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "quickstart.ipynb"
SELFTRAINING = NOTEBOOK.with_name("selftraining.ipynb")


def _run_tiny(path: Path, tmp_path: Path, monkeypatch) -> "nbformat.NotebookNode":
    """Execute a notebook top to bottom with its tiny settings (work under tmp_path/work); no cell may fail."""
    from jupyter_client.kernelspec import KernelSpecManager

    if "python3" not in KernelSpecManager().find_kernel_specs():
        pytest.skip("no python3 Jupyter kernel (python -m ipykernel install --user)")
    monkeypatch.setenv("LABELSYNTH_NOTEBOOK_TINY", "1")
    monkeypatch.setenv("LABELSYNTH_NOTEBOOK_DIR", str(tmp_path / "work"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, kernel_name="python3", timeout=900, resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    return nb


@pytest.mark.slow
def test_quickstart_notebook_runs(tmp_path, monkeypatch):
    nb = _run_tiny(NOTEBOOK, tmp_path, monkeypatch)
    out = tmp_path / "work" / "out"
    report = json.loads((out / "report.json").read_text())
    assert len(report["frames"]) == 6
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "annotated:" in text and "wound bed" in text


@pytest.mark.slow
def test_selftraining_notebook_runs(tmp_path, monkeypatch):
    """expand -> train -> segment a new video -> expand --labels both -> train again, tiny settings."""
    nb = _run_tiny(SELFTRAINING, tmp_path, monkeypatch)
    work = tmp_path / "work"
    assert (work / "model1" / "model.onnx").is_file() and (work / "model2" / "model.onnx").is_file()
    assert len(list((work / "B" / "predictions").glob("*.png"))) == 6  # the first model's masks of the new video
    assert json.loads((work / "B_out" / "run.json").read_text())["labels"] == "both"
    report = json.loads((work / "model2" / "train.json").read_text())
    assert len(report["sources"]) == 2
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "model1: wound bed" in text and "model2: wound bed" in text
