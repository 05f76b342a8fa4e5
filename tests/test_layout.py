"""The house rules of ``src/jaxdea`` (docs/architecture.md), checked on its import graph.

The graph is built with :mod:`ast` from every ``import`` statement, function-level imports
included. It fails on:

- an import cycle between modules;
- a private (underscore) name imported from another module;
- an import from a higher wing (the wing order is :data:`WINGS`, lowest first);
- a source file over :data:`MAX_LINES` lines;
- an ``importlib.import_module`` / ``__import__`` call (an import the graph cannot see).

The checker itself is tested on a small tree with one planted violation of each kind, so a
rule that silently stopped working would fail here too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: Wings, lowest first: a module imports only from its own wing or a lower one. ``api`` is
#: the root package (``jaxdea/__init__.py``), which gathers the public API of every wing
#: below it; only the CLI stands above it.
WINGS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("leaves", ("_checks", "solver", "materials", "membrane", "geometry", "electrical",
                "signals", "payloads", "params", "provenance")),
    ("models", ("models",)),
    ("config", ("config",)),
    ("engine", ("engine",)),
    ("studies", ("studies",)),
    ("calibration", ("calibration",)),
    ("plotting", ("plotting",)),
    ("reproduce", ("reproduce",)),
    ("api", ("",)),
    ("cli", ("cli",)),
)
MAX_LINES = 500


def modules(src: Path, package: str) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of ``package`` under ``src``."""
    out = {}
    for path in sorted((src / package).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def wing_of(module: str, package: str) -> int:
    """Rank of ``module``'s wing in :data:`WINGS` (ValueError when it is in none)."""
    rel = module[len(package) + 1:] if module != package else ""
    first = rel.split(".")[0]
    for rank, (_, members) in enumerate(WINGS):
        if first in members:
            return rank
    raise ValueError(f"{module} belongs to no wing: add it to WINGS and docs/architecture.md")


def imports(module: str, path: Path, mods: dict[str, Path], package: str):
    """``(target module, imported name or None, line)`` of every import of ``package`` in
    ``path``, and the lines of hidden (``import_module``/``__import__``) imports."""
    is_pkg = path.name == "__init__.py"
    tree = ast.parse(path.read_text())
    found, hidden = [], []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target != package and not target.startswith(package + "."):
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in mods:  # "from pkg import submodule"
                    found.append((sub, None, node.lineno))
                else:
                    found.append((target, alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == package or alias.name.startswith(package + "."):
                    found.append((alias.name, None, node.lineno))
        elif isinstance(node, ast.Call):
            fn = node.func
            name = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if name in ("import_module", "__import__"):
                hidden.append(node.lineno)
    return found, hidden


def violations(src: Path, package: str) -> list[str]:
    """Every breach of the house rules in ``src/package``, one line each."""
    mods = modules(src, package)
    bad, edges = [], {m: set() for m in mods}
    for mod, path in mods.items():
        n = len(path.read_text().splitlines())
        if n > MAX_LINES:
            bad.append(f"file over {MAX_LINES} lines: {path.relative_to(src)} ({n})")
        try:
            rank = wing_of(mod, package)
        except ValueError as exc:
            bad.append(str(exc))
            continue
        found, hidden = imports(mod, path, mods, package)
        bad += [f"hidden import: {path.relative_to(src)}:{ln}" for ln in hidden]
        for target, name, line in found:
            if target not in mods:
                bad.append(f"import of a missing module: {path.relative_to(src)}:{line} {target}")
                continue
            if target != mod:
                edges[mod].add(target)
            if name and name.startswith("_") and not name.startswith("__") and target != mod:
                bad.append(f"private import: {path.relative_to(src)}:{line} {name} from {target}")
            if wing_of(target, package) > rank:
                bad.append(f"upward import: {path.relative_to(src)}:{line} {mod} "
                           f"({WINGS[rank][0]}) imports {target} "
                           f"({WINGS[wing_of(target, package)][0]})")
    bad += [f"import cycle: {' -> '.join(c)}" for c in cycles(edges)]
    return bad


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted.

    A package's ``__init__`` imports its own modules; a module that imports back from its
    package (``from . import x``) would close a loop and is reported like any other."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in edges:
        if v not in index:
            strong(v)
    return out


def test_jaxdea_keeps_the_house_rules():
    bad = violations(SRC, "jaxdea")
    assert not bad, "\n".join(bad)


def test_every_module_is_in_a_wing_and_the_api_is_the_root():
    mods = modules(SRC, "jaxdea")
    assert len(mods) > 20
    ranks = {m: wing_of(m, "jaxdea") for m in mods}
    assert ranks["jaxdea"] == [w for w, _ in WINGS].index("api")
    assert ranks["jaxdea.engine.lanes"] > ranks["jaxdea.models.cone"] > ranks["jaxdea.solver"]


def _plant(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / "pkg" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


@pytest.mark.parametrize("files, expected", [
    ({"models/a.py": "from ..engine.b import run\n", "engine/b.py": "def run(): ...\n"},
     "upward import"),
    ({"engine/a.py": "def f():\n    from .b import g\n", "engine/b.py": "from .a import f\n"},
     "import cycle"),
    ({"engine/a.py": "from ..models.m import _secret\n", "models/m.py": "_secret = 1\n"},
     "private import"),
    ({"models/long.py": "x = 1\n" * (MAX_LINES + 1)}, "file over"),
    ({"config/c.py": "import importlib\nimportlib.import_module('pkg.cli')\n"},
     "hidden import"),
    ({"stray/x.py": "x = 1\n"}, "belongs to no wing"),
])
def test_the_checker_catches_each_planted_violation(tmp_path, files, expected):
    files = {"__init__.py": "", "models/__init__.py": "", "engine/__init__.py": "",
             "config/__init__.py": "", "stray/__init__.py": "", **files}
    bad = violations(_plant(tmp_path, files), "pkg")
    assert any(expected in line for line in bad), bad


def test_a_clean_planted_tree_passes(tmp_path):
    files = {"__init__.py": "from .engine.b import run\n", "models/__init__.py": "",
             "engine/__init__.py": "", "models/m.py": "def law(): ...\n",
             "engine/b.py": "from ..models.m import law\n\ndef run():\n    from . import c\n",
             "engine/c.py": "from ..models import m\n"}
    assert violations(_plant(tmp_path, files), "pkg") == []
