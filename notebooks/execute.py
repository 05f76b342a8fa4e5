"""Run a notebook top to bottom and store its outputs, without Jupyter.

    python notebooks/execute.py NOTEBOOK.ipynb

The code cells run in order in one namespace, with the notebook's folder as the working
directory (as in Jupyter) and matplotlib's non-interactive Agg backend, exactly as
``tests/test_notebooks.py`` runs them (lines starting with ``%`` or ``!`` are dropped). For
each code cell the printed text is stored as a ``stream`` output and every figure still open
after the cell as a ``display_data`` PNG; the figures are then closed. The value of a cell's
last expression is not shown (print it). Environment variables reach the cells, so
``JAXDEA_NOTEBOOK_SMALL=1 python notebooks/execute.py ...`` runs the small version.

On an error the run stops, the cell number and traceback are printed, the notebook file is
left as it was and the exit status is 1. Only the standard library and matplotlib are used.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import sys
import time
import traceback
from pathlib import Path


def cell_source(cell: dict) -> str:
    """The cell's code without IPython magics and shell lines (``%...``, ``!...``)."""
    src = cell["source"]
    src = "".join(src) if isinstance(src, list) else src
    return "\n".join(line for line in src.splitlines()
                     if not line.lstrip().startswith(("%", "!")))


def lines(text: str) -> list[str]:
    """Text as nbformat stores it: a list of lines, each with its newline."""
    return text.splitlines(keepends=True)


def figure_outputs(plt) -> list[dict]:
    """Every open figure as a ``display_data`` output (PNG), then close them all."""
    out = []
    for num in plt.get_fignums():
        fig = plt.figure(num)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", bbox_inches="tight")
        out.append({"output_type": "display_data", "metadata": {},
                    "data": {"image/png": base64.b64encode(buf.getvalue()).decode("ascii"),
                             "text/plain": [repr(fig)]}})
    plt.close("all")
    return out


def execute(path: Path) -> dict | None:
    """Run the notebook at ``path``; the notebook with outputs, or None after an error."""
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    nb = json.loads(path.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    ns = {"__name__": "__main__"}
    os.chdir(path.parent)
    sys.path.insert(0, str(path.parent))
    for i, cell in enumerate(code):
        start = time.perf_counter()
        buf = io.StringIO()
        try:
            with contextlib.redirect_stdout(buf):
                exec(compile(cell_source(cell), f"{path.name} cell {i}", "exec"), ns)
        except BaseException:
            sys.stdout.write(buf.getvalue())
            print(f"\nerror in code cell {i} (of {len(code)}, counting from 0) of {path}:",
                  file=sys.stderr)
            traceback.print_exc()
            print(f"{path} was not changed", file=sys.stderr)
            return None
        outputs = []
        if buf.getvalue():
            outputs.append({"output_type": "stream", "name": "stdout",
                            "text": lines(buf.getvalue())})
        outputs += figure_outputs(plt)
        cell["outputs"] = outputs
        cell["execution_count"] = i + 1
        print(f"cell {i + 1}/{len(code)}: {time.perf_counter() - start:.1f} s",
              file=sys.stderr)
    return nb


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not argv[0].endswith(".ipynb"):
        print("usage: python notebooks/execute.py NOTEBOOK.ipynb", file=sys.stderr)
        return 2
    path = Path(argv[0]).resolve()
    start = time.perf_counter()
    nb = execute(path)
    if nb is None:
        return 1
    text = json.dumps(nb, indent=1, sort_keys=True, ensure_ascii=False) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    print(f"{path.name}: executed in {time.perf_counter() - start:.1f} s, outputs written",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
