"""jaxdea against the independent numpy/scipy transcription (tests/scipy_reference.py).

Every configuration and drive case of paper 000 is run through ``jaxdea.sweep`` (one call,
three frequencies, one of them near the case's resonance) and through
``scipy_reference.reference_metrics`` (LSODA, rtol 1e-9) with the same protocol: 20 cycles
from rest, metrics averaged over the last 5 (the paper uses 100; 20 keeps the test fast and
both codes see exactly the same transient). Payload M = 2 g, c = 0.1 N s/m (plus one
heavily damped case, c = 10, for DCDEA-LS drive A).

Compile cost: every sweep has a 3-element frequency axis and the same cycles/average, so
jaxdea compiles once per configuration (three compiles in all).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import jaxdea
import scipy_reference as ref

MASS = 2e-3  # kg, payload M
CYCLES = 20
AVERAGE = 5
RTOL_POWER = 5e-3  # P_out, P_in, P_in_signed
RTOL_AMPLITUDE = 1e-2  # amplitude, v_rms

D0 = 4e-3  # m
L_R = 8e-3  # m

# (config, drive, phase, damping, three frequencies). Resonances located with a coarse
# (3 Hz, 20-cycle) jaxdea sweep; the middle/high entries sit on the peaks.
CASES = [
    ("scdea_ls", "A", 0.0, 0.1, (20.0, 86.0, 129.0)),
    ("dcdea_rr", "A", 0.0, 0.1, (20.0, 71.0, 129.0)),
    ("dcdea_rr", "both", math.pi, 0.1, (20.0, 71.0, 129.0)),
    ("dcdea_ls", "A", 0.0, 0.1, (20.0, 70.0, 129.0)),
    ("dcdea_ls", "A", 0.0, 10.0, (20.0, 70.0, 120.0)),
    ("dcdea_ls", "B", 0.0, 0.1, (20.0, 71.0, 129.0)),
    ("dcdea_ls", "both", 0.0, 0.1, (20.0, 70.0, 128.0)),
    ("dcdea_ls", "both", math.pi, 0.1, (20.0, 68.0, 128.0)),
    ("dcdea_ls", "both", 1.0, 0.1, (20.0, 71.0, 131.0)),
]


def _case_id(case):
    cfg, drive, phase, c, _ = case
    ph = "" if drive != "both" else f"-phase{phase:.3g}"
    return f"{cfg}-{drive}{ph}-c{c:g}"


def _check_sweep_sanity(ds):
    """Invariants every returned sweep must satisfy."""
    status = ds.status.values
    assert np.all(status == 0), f"status {status}"
    p_out = ds.P_out.values
    p_in = ds.P_in.values
    eff = ds.efficiency.values
    assert np.all(np.isfinite(p_out)) and np.all(np.isfinite(p_in))
    assert np.all(p_out >= 0.0), p_out
    assert np.all(p_in >= p_out), (p_in, p_out)
    assert np.all((eff >= 0.0) & (eff <= 1.0)), eff


def _rel(a, b):
    return abs(a - b) / abs(b)


@pytest.mark.parametrize("case", CASES, ids=[_case_id(c) for c in CASES])
def test_sweep_matches_scipy_reference(models, case):
    cfg, drive, phase, damping, freqs = case
    freqs = np.asarray(freqs)
    ds = jaxdea.sweep(models[cfg], mass=MASS, damping=damping, freq=freqs, drive=drive,
                      phase=phase, cycles=CYCLES, average=AVERAGE)
    _check_sweep_sanity(ds)
    np.testing.assert_array_equal(ds.f.values, freqs)

    tolerances = {"P_out": RTOL_POWER, "P_in": RTOL_POWER, "P_in_signed": RTOL_POWER,
                  "amplitude": RTOL_AMPLITUDE, "v_rms": RTOL_AMPLITUDE}
    worst = {k: 0.0 for k in tolerances}
    failures = []
    for i, f in enumerate(freqs):
        r = ref.reference_metrics(cfg, MASS, damping, float(f), drive=drive, phase=phase,
                                  cycles=CYCLES, average=AVERAGE, rtol=1e-9, method="LSODA")
        assert r["P_in"] >= r["P_out"] >= 0.0
        for name, tol in tolerances.items():
            got = float(ds[name].values[i])
            err = _rel(got, r[name])
            worst[name] = max(worst[name], err)
            if not err <= tol:
                failures.append(f"{name} at {f:g} Hz: jaxdea {got:.6g} vs scipy "
                                f"{r[name]:.6g} (rel err {err:.3%} > {tol:.1%})")
    print(f"\n[{_case_id(case)}] max rel err: "
          + ", ".join(f"{k} {v:.2e}" for k, v in worst.items()))
    assert not failures, "; ".join(failures)


# ---------------------------------------------------------------------------
# Static equilibria
# ---------------------------------------------------------------------------

def test_preload_matches_reference(models):
    f0_ref = ref.preload()
    assert f0_ref == pytest.approx(1.5189, abs=5e-4)
    for cfg in ("scdea_ls", "dcdea_ls"):
        f0 = float(models[cfg].actuator.preload)
        assert f0 == pytest.approx(1.52, abs=0.01), cfg
        assert f0 == pytest.approx(1.5189, abs=5e-4), cfg
        assert f0 == pytest.approx(f0_ref, rel=1e-9), cfg
        assert f0 == pytest.approx(ref.static_equilibrium(cfg)["F0"], rel=1e-9), cfg


@pytest.mark.parametrize("cfg, expected, ref_keys", [
    ("scdea_ls", [D0], ["d"]),
    ("dcdea_rr", [L_R / 2], ["d_B"]),
    ("dcdea_ls", [-D0, D0], ["d_A", "d_B"]),
])
def test_static_equilibrium(models, cfg, expected, ref_keys):
    act = models[cfg].actuator
    q = np.asarray(act.equilibrium())
    assert q.shape == (len(expected),)
    np.testing.assert_allclose(q, expected, rtol=0, atol=1e-9)
    # the relaxed, uncharged membranes and the spring balance there ...
    np.testing.assert_allclose(np.asarray(act.static_forces(q)), 0.0, rtol=0, atol=1e-9)
    # ... and at the nominal positions themselves
    np.testing.assert_allclose(np.asarray(act.static_forces(np.asarray(expected))), 0.0,
                               rtol=0, atol=1e-9)
    # same answer as the scipy transcription's fsolve
    eq = ref.static_equilibrium(cfg)
    np.testing.assert_allclose(q, [eq[k] for k in ref_keys], rtol=0, atol=1e-9)
    if cfg == "dcdea_rr":
        np.testing.assert_allclose(np.asarray(act.deflections(q)), [-D0, D0], rtol=0,
                                   atol=1e-9)


def test_single_cone_rejects_membrane_b(models):
    for drive in ("B", "both"):
        with pytest.raises(jaxdea.SweepError):
            jaxdea.sweep(models["scdea_ls"], mass=MASS, damping=0.1, freq=[50.0],
                         drive=drive, cycles=CYCLES, average=AVERAGE)


def test_low_frequency_P_in_matches_lsoda(models):
    """P_in without recovery at 1-2 Hz, where it integrates the current's tiny negative part
    over the long slow phases of a cycle (``engine.step_control.charge_weight``). With the
    charge's error weight fixed at 1e-1 this was off by 1.2e-3 here (3.8e-3 at 1 Hz over 100
    cycles, M 0.26 g, c 0.26 N s/m); the bar is the map's accuracy target, 3e-4."""
    mass, damping, freqs = 2.6e-4, 0.26, np.array([1.0, 2.0])
    ds = jaxdea.sweep(models["dcdea_ls"], mass=mass, damping=damping, freq=freqs, cycles=10,
                      average=2, early_exit=None)
    for i, f in enumerate(freqs):
        r = ref.reference_metrics("dcdea_ls", mass, damping, float(f), cycles=10, average=2,
                                  rtol=1e-9, method="LSODA")
        for name in ("P_out", "P_in", "P_in_signed"):
            assert _rel(float(ds[name].values[i]), r[name]) < 3e-4, (f, name)


@pytest.mark.parametrize("mass, damping, freq", [(2e-3, 0.1, 129.0), (0.26e-3, 0.26, 5.0)])
def test_exponential_solver_matches_lsoda_in_fewer_steps(mass, damping, freq):
    """``StepControl(solver="exponential")`` (Krogstad's exponential RK4): P_out and P_in
    within 1e-4 of LSODA (rtol 1e-10) on DCDEA-LS at the upper resonance and at 5 Hz, where
    the low-frequency charge weight acts, in fewer steps than the default Lawson RK4 at the
    same rtol (measured 1705 / 2043 and 3758 / 3945; errors 1.3e-5 and 2.9e-5)."""
    model = jaxdea.load_config(Path(__file__).parents[1] / "configs" / "dcdea_ls.toml")
    r = ref.reference_metrics("dcdea_ls", mass, damping, freq, cycles=20, average=5, rtol=1e-10)
    steps = {}
    for solver in ("lawson", "exponential"):
        ds = jaxdea.sweep(model, mass=mass, damping=damping, freq=[freq], cycles=20, average=5,
                          control=jaxdea.StepControl(solver=solver))
        assert int(ds.status[0]) == 0 and ds.attrs["solver"] == solver
        steps[solver] = int(ds.steps[0])
        for k in ("P_out", "P_in"):
            assert abs(float(ds[k][0]) / r[k] - 1) < 1e-4, (solver, k, float(ds[k][0]), r[k])
    assert steps["exponential"] < steps["lawson"], steps
