"""Single-precision lanes (``StepControl(precision="single")``) against the float64 engine."""

from pathlib import Path

import numpy as np
import pytest

import jaxdea
from jaxdea.engine.precision import NARROWED

LS = Path(__file__).resolve().parents[1] / "configs" / "dcdea_ls.toml"

FREQ = np.array([2.0, 20.0, 60.0, 150.0])


@pytest.fixture(scope="module")
def pair():
    model = jaxdea.load_config(LS)
    kw = dict(mass=2e-3, damping=1.0, freq=FREQ, cycles=30, average=3, early_exit=None)
    return (jaxdea.sweep(model, **kw),
            jaxdea.sweep(model, control=jaxdea.StepControl(precision="single"), **kw))


def test_single_precision_agrees_with_double(pair):
    """Issue 16's target: P_out and P_in within 1e-3 of float64 (same steps, same tolerance)."""
    double, single = pair
    # measured <= 2e-5, except P_in at 2 Hz (7.5e-4): single keeps the charge's fixed error
    # weight there (engine.precision), double tightens it; the issue asks <= 1e-3
    for name, bar in (("P_out", 2e-4), ("P_in", 1e-3), ("amplitude", 2e-4)):
        rel = np.abs(single[name].values / double[name].values - 1)
        assert rel.max() < bar, (name, rel)
    assert (single.status.values == 0).all()
    # with equal error weights (>= 30 Hz) the step-size control sees the same errors: the
    # step counts agree to a few per cent
    high = FREQ >= 30.0
    np.testing.assert_allclose(single.steps.values[high], double.steps.values[high], rtol=0.05)
    # and the answer really is single: not bit-identical, and off by more than float64 noise
    assert np.abs(single.P_out.values / double.P_out.values - 1).max() > 1e-9


def test_single_precision_results_are_float64(pair):
    _, single = pair
    assert all(single[v].dtype == np.float64 for v in ("P_out", "P_in", "residual"))
    assert set(NARROWED) == {"q", "v", "charge", "xi_m", "xi_el"}


def test_precision_is_recorded(pair, monkeypatch):
    """A map's attrs (and so its store's settings, which a resume must match) say which
    precision computed it: a float32 store is not resumed by a float64 run, nor mixed."""
    from jaxdea.studies import powermap as pm
    from jaxdea.studies.sweep import VARIABLES

    double, single = pair
    assert (double.attrs["precision"], single.attrs["precision"]) == ("double", "single")
    monkeypatch.setattr(pm, "_run_chunk", lambda model, loadings, *a, **k: {
        v: np.zeros(loadings.drive.frequency.shape[0]) for v in VARIABLES})
    ds = jaxdea.powermap(jaxdea.load_config(LS), mass=[1e-3], damping=[1.0], freq=[60.0],
                         control=jaxdea.StepControl(precision="single"), early_exit=None,
                         progress=False)
    assert ds.attrs["precision"] == "single"
