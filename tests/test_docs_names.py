"""Every ``jaxdea.x.y`` name that the README, the docs and the notebooks write in backticks
resolves: a module, or an attribute of one (issue 12: what the docs name is reachable)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
         *sorted((ROOT / "notebooks").glob("*.ipynb"))]
WINGS = "models|engine|studies|calibration|config|cli|reproduce"
NAME = re.compile(r"`(jaxdea(?:\.[A-Za-z_]\w*)+)")
#: a name written relative to the package, e.g. `engine.periodic.SHOOTING_LANES`
SHORT = re.compile(rf"`((?:{WINGS})\.(?!md`)[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)")
#: a source file, e.g. `models/cone.py` or `studies/transient.py`
FILE = re.compile(rf"`((?:{WINGS})/\w+\.py)")


def _names() -> list[str]:
    found = set()
    for path in TEXTS:
        text = path.read_text()
        found |= set(NAME.findall(text)) | {f"jaxdea.{m}" for m in SHORT.findall(text)}
    return sorted(found)


def _files() -> list[str]:
    return sorted({m for path in TEXTS for m in FILE.findall(path.read_text())})


def _resolve(dotted: str):
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):  # the longest importable module prefix
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(dotted)


def test_the_docs_name_something():
    assert len(_names()) > 10


@pytest.mark.parametrize("dotted", _names())
def test_every_name_in_the_docs_resolves(dotted):
    _resolve(dotted)


@pytest.mark.parametrize("rel", _files())
def test_every_source_file_in_the_docs_exists(rel):
    assert (ROOT / "src" / "jaxdea" / rel).is_file()
