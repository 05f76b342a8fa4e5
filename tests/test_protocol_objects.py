"""Protocol objects (Paper, Continuation, Periodic) against the string protocols they replace.

- each object checks its settings when built (SweepError naming the field and its range);
- ``as_protocol`` maps a name and the studies' keywords onto the object;
- sweep, powermap and run_cells give exactly the string form's results (np.array_equal,
  attrs included) with an object, and reject a keyword that conflicts with one.

DCDEA-LS at 60-140 Hz, <= 10 cycles: seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import jaxdea
from jaxdea import Continuation, Paper, Periodic, SweepError
from jaxdea.engine.batch import run_cells
from jaxdea.engine.protocols import EARLY_EXIT, as_keywords, as_protocol
from jaxdea.studies.loadings import make_loadings

CONFIG = Path(__file__).parents[1] / "configs" / "dcdea_ls.toml"
FREQ = np.array([60.0, 100.0, 140.0])
PAYLOAD = dict(mass=2e-3, damping=0.1)


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


def _assert_same(a, b):
    assert a.attrs == b.attrs
    assert set(a.data_vars) == set(b.data_vars)
    for k in a.data_vars:
        assert np.array_equal(a[k].values, b[k].values, equal_nan=True), k


# ---- validation -----------------------------------------------------------------------------

@pytest.mark.parametrize("make, field", [
    (lambda: Paper(cycles=0), "cycles"),
    (lambda: Paper(cycles=2.5), "cycles"),
    (lambda: Paper(cycles=4, average=5), "average"),
    (lambda: Paper(average=0), "average"),
    (lambda: Paper(early_exit=1.5), "early_exit"),
    (lambda: Continuation(early_exit=0.0), "early_exit"),
    (lambda: Continuation(cycles=True), "cycles"),
    (lambda: Continuation(direction="up"), "direction"),
    (lambda: Periodic(tol=0), "tol"),
    (lambda: Periodic(tol=float("nan")), "tol"),
])
def test_objects_validate_their_fields(make, field):
    with pytest.raises(SweepError, match=field):
        make()


def test_objects_are_frozen_and_default_as_the_strings():
    p = Paper()
    with pytest.raises(AttributeError):
        p.cycles = 3
    assert p == Paper(cycles=100, average=5, early_exit=EARLY_EXIT)
    assert Continuation().direction == "forward"
    assert Periodic().tol == 1e-6
    assert {"Paper", "Continuation", "Periodic"} <= set(jaxdea.__all__)


def test_as_protocol_maps_names_and_keywords():
    kw = dict(cycles=10, average=2, early_exit=None, direction="backward", tol=1e-4)
    assert as_protocol("paper", **kw) == Paper(cycles=10, average=2, early_exit=None)
    assert as_protocol("continuation", **kw) == Continuation(10, 2, None, "backward")
    assert as_protocol("periodic", **kw) == Periodic(tol=1e-4)
    assert as_protocol("paper") == Paper()
    obj = Continuation(cycles=10, average=2)
    assert as_protocol(obj) is obj
    assert as_protocol(obj, cycles=100, tol=1e-6) is obj  # keywords at their defaults
    with pytest.raises(SweepError, match="protocol"):
        as_protocol("steady")
    with pytest.raises(SweepError, match="protocol"):
        as_protocol(None)
    with pytest.raises(SweepError, match="cycle"):
        as_protocol("paper", cycle=10)
    with pytest.raises(SweepError, match="average"):
        as_protocol("paper", cycles=3, average=4)  # a string's settings are checked too
    # the studies' bridge: strings pass through unchanged, objects give their settings
    assert as_keywords("paper", cycles=7, tol=0.5) == ("paper", (7, 0.5))
    assert as_keywords(Periodic(tol=1e-4), cycles=100, tol=1e-6) == ("periodic", (100, 1e-4))


@pytest.mark.parametrize("keyword, value, obj", [
    ("cycles", 10, Paper()),
    ("average", 2, Continuation()),
    ("early_exit", None, Paper()),
    ("direction", "backward", Continuation(direction="forward")),
    ("tol", 1e-4, Periodic()),
    ("tol", 1e-4, Paper()),  # not a setting of Paper at all
])
def test_conflicting_keyword_is_rejected(model, keyword, value, obj):
    with pytest.raises(SweepError, match=f"^{keyword} = .* conflicts with protocol"):
        jaxdea.sweep(model, **PAYLOAD, freq=FREQ, protocol=obj, **{keyword: value})
    with pytest.raises(SweepError, match=f"^{keyword} = .* conflicts with protocol"):
        jaxdea.powermap(model, mass=[2e-3], damping=[0.1], freq=FREQ, protocol=obj,
                        progress=False, **{keyword: value})
    if keyword != "direction":  # run_cells takes chains (successor), not a direction
        loads = make_loadings(model, 2e-3, 0.1, FREQ)
        with pytest.raises(SweepError, match=f"^{keyword} = .* conflicts with protocol"):
            run_cells(model, loads, protocol=obj, **{keyword: value})


# ---- same results as the strings -------------------------------------------------------------

@pytest.mark.parametrize("obj, legacy", [
    (Paper(cycles=10, average=2), dict(protocol="paper", cycles=10, average=2)),
    (Paper(cycles=8, average=3, early_exit=None),
     dict(protocol="paper", cycles=8, average=3, early_exit=None)),
    (Continuation(cycles=10, average=2, direction="backward"),
     dict(protocol="continuation", cycles=10, average=2, direction="backward")),
    (Periodic(tol=1e-5), dict(protocol="periodic", tol=1e-5)),
])
def test_sweep_with_object_equals_string(model, obj, legacy):
    a = jaxdea.sweep(model, **PAYLOAD, freq=FREQ, protocol=obj)
    b = jaxdea.sweep(model, **PAYLOAD, freq=FREQ, **legacy)
    _assert_same(a, b)
    assert a.attrs["protocol"] == obj.name


@pytest.mark.parametrize("obj, legacy", [
    (Paper(cycles=10, average=2), dict(protocol="paper", cycles=10, average=2)),
    (Continuation(cycles=10, average=2, direction="backward"),
     dict(protocol="continuation", cycles=10, average=2, direction="backward")),
])
def test_powermap_with_object_equals_string(model, obj, legacy):
    grid = dict(mass=[1e-3, 2e-3], damping=[0.1], freq=FREQ, progress=False)
    a = jaxdea.powermap(model, **grid, protocol=obj)
    b = jaxdea.powermap(model, **grid, **legacy)
    _assert_same(a, b)


def test_run_cells_with_object_equals_string(model):
    loads = make_loadings(model, 2e-3, 0.1, FREQ)
    a = run_cells(model, loads, protocol=Paper(cycles=10, average=2, early_exit=None))
    b = run_cells(model, loads, protocol="paper", cycles=10, average=2, early_exit=None)
    for k in ("P_out", "P_in", "amplitude", "status", "steps", "cycles_run"):
        assert np.array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k))), k
    assert np.all(np.asarray(a.cycles_run) == 10)
