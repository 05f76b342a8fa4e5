"""ruff (configured in pyproject.toml) is clean on the package, the tests and the benches."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_is_clean():
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    assert Path(ruff).exists(), "ruff is a test dependency: pip install -e '.[test]'"
    out = subprocess.run([ruff, "check", "src", "tests", "bench"], cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_package_ships_its_type_marker():
    assert (ROOT / "src" / "jaxdea" / "py.typed").is_file()
