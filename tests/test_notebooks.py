"""Every notebook runs top to bottom (at the reduced size CI can afford).

Jupyter is not a dependency, so the code cells are executed in order in one namespace, in a
subprocess whose working directory is ``notebooks/`` (as in Jupyter), with the non-interactive
matplotlib backend and ``JAXDEA_NOTEBOOK_SMALL=1`` (notebooks shrink their grids when set).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))

RUNNER = """
import json, sys
import matplotlib
matplotlib.use("Agg")
nb = json.load(open(sys.argv[1]))
ns = {"__name__": "__main__"}
for i, cell in enumerate(c for c in nb["cells"] if c["cell_type"] == "code"):
    src = "".join(cell["source"])
    src = "\\n".join(l for l in src.splitlines() if not l.lstrip().startswith(("%", "!")))
    exec(compile(src, f"{sys.argv[1]} cell {i}", "exec"), ns)
print("notebook ok")
"""


def test_there_are_notebooks():
    assert NOTEBOOKS, "notebooks/ has no .ipynb"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path):
    nb = json.loads(path.read_text())
    assert any(c["cell_type"] == "markdown" for c in nb["cells"]), "explain the notebook"
    # the suite's on-disk cache of compiled programs (conftest.py): a notebook's programs
    # are compiled once per machine, not once per run
    env = dict(os.environ, JAXDEA_NOTEBOOK_SMALL="1", MPLBACKEND="Agg",
               PYTHONPATH=str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", ""),
               JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1.0")
    env.pop("XLA_FLAGS", None)
    res = subprocess.run([sys.executable, "-c", RUNNER, str(path)], cwd=path.parent, env=env,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "notebook ok" in res.stdout
