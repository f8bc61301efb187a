"""Execute every notebook in notebooks/ at small size: the notebooks are part of the suite.

Each notebook reads its size from environment variables named ``SCATMODES_NB_*`` (e.g.
``SCATMODES_NB_RAYS``); the values below make every notebook run in well under a minute.
``SCATMODES_NB_SMALL=1`` is set as well, for notebooks that prefer one switch. Matplotlib
runs on the Agg backend. Notebooks are executed in a fresh ``python3`` kernel of the
interpreter running the tests (jupyter_client starts kernelspecs whose command is
``python`` with ``sys.executable``), in a temporary copy of the folder, so nothing they
write lands in the repository; outputs are never saved back.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
PATHS = sorted(NOTEBOOKS.glob("*.ipynb")) if NOTEBOOKS.is_dir() else []

#: small sizes for the test run (read by the notebooks through os.environ)
SMALL = {
    "SCATMODES_NB_SMALL": "1",
    "SCATMODES_NB_RAYS": "4000",
    "SCATMODES_NB_RESOLUTION": "64",
    "MPLBACKEND": "Agg",
    "JUPYTER_PLATFORM_DIRS": "1",  # silences jupyter_core's path-migration warning
    "PYDEVD_DISABLE_FILE_VALIDATION": "1",  # frozen-modules note of the debugger on 3.11
}

#: seconds per notebook cell (the whole notebook should take < 60 s at the sizes above)
CELL_TIMEOUT = 120


def _committed_clean(nb) -> list[int]:
    """Indices of code cells that carry outputs or an execution count (must be none)."""
    return [i for i, c in enumerate(nb.cells) if c.cell_type == "code"
            and (c.get("outputs") or c.get("execution_count") is not None)]


@pytest.mark.skipif(not PATHS, reason="no notebooks in notebooks/")
@pytest.mark.parametrize("path", PATHS, ids=[p.name for p in PATHS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat", reason="nbformat is not installed")
    for key, val in SMALL.items():
        monkeypatch.setenv(key, val)
    try:
        from jupyter_client.kernelspec import NoSuchKernel
        from nbclient import NotebookClient
        from nbclient.exceptions import CellExecutionError
    except ImportError as err:
        pytest.skip(f"nbclient is not installed ({err})")
    nb = nbformat.read(path, as_version=4)
    assert not _committed_clean(nb), f"{path.name}: commit notebooks without outputs"
    work = tmp_path / "notebooks"
    shutil.copytree(NOTEBOOKS, work)
    client = NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3",
                            resources={"metadata": {"path": str(work)}})
    try:
        client.execute()
    except NoSuchKernel as err:
        pytest.skip(f"no python3 Jupyter kernel for {sys.executable} ({err})")
    except CellExecutionError as err:
        pytest.fail(f"{path.name} failed:\n{err}", pytrace=False)
