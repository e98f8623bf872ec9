"""Every research notebook in `experiments/notebooks/` (jupytext percent-format `.py`) is a valid notebook and runs
top to bottom as one, with its small settings (`PIEZOJAX_NOTEBOOK_SMALL=1`): nbclient executes it in a fresh
kernel, so the asserts inside each notebook (its checks on its own results) run too."""

from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "experiments" / "notebooks").glob("[0-9][0-9]_*.py"))


def test_the_notebooks_are_there():
    # the stories issue 18 asks for: quickstart, own data, self-sensing, compensation and control, scale
    names = [p.stem for p in NOTEBOOKS]
    assert names == ["01_quickstart", "02_your_own_data", "03_self_sensing", "04_compensation_and_control",
                     "05_scale"]


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch):
    import jupytext
    import nbformat
    from nbclient import NotebookClient

    nb = jupytext.read(path)
    nbformat.validate(nb)
    assert sum(c.cell_type == "markdown" for c in nb.cells) >= 4  # a story, not a script
    assert sum(c.cell_type == "code" for c in nb.cells) >= 4
    monkeypatch.setenv("PIEZOJAX_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # the kernel and the command line run by notebook 02 share the test run's compilation cache ($PIEZOJAX_CACHE_DIR,
    # tests/conftest.py)
    client = NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}})
    client.execute()  # raises CellExecutionError (with the cell and traceback) on the first failing cell
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any(o.get("output_type") == "stream" for o in outputs)  # it printed its numbers
