"""Every notebook in notebooks/ runs top to bottom at its small size, so none can silently rot.

Each notebook's first code cell reads ``SMALL = os.environ.get("JAXLOC_NOTEBOOK_SIZE", "full") ==
"small"``; the test sets ``JAXLOC_NOTEBOOK_SIZE=small`` and ``MPLBACKEND=Agg`` and executes it with
nbclient in a fresh kernel (working directory: notebooks/). A failing cell fails the test with the
cell's source and error.
"""

from __future__ import annotations

from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
SIZE_CELL = 'SMALL = os.environ.get("JAXLOC_NOTEBOOK_SIZE", "full") == "small"'
CELL_TIMEOUT_S = 600


def test_there_are_notebooks():
    names = {path.name for path in NOTEBOOKS}
    assert {"sg2loc_sweep.ipynb", "m2loc_sweep.ipynb", "walkthrough.ipynb"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[path.stem for path in NOTEBOOKS])
def test_notebook_is_clean_and_sized(path):
    notebook = nbformat.read(path, as_version=4)
    nbformat.validate(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert code and SIZE_CELL in code[0].source, "first code cell must read JAXLOC_NOTEBOOK_SIZE"
    for cell in code:
        assert not cell.outputs and cell.execution_count is None, "commit notebooks without outputs"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[path.stem for path in NOTEBOOKS])
def test_notebook_runs_at_small_size(path, monkeypatch):
    monkeypatch.setenv("JAXLOC_NOTEBOOK_SIZE", "small")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        notebook,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as error:
        pytest.fail(f"{path.name} failed:\n{error}", pytrace=False)
