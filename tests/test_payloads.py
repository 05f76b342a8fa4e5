"""Payload laws (issue 17): jaxdea.Drag, Elastic and Gravity against the independent scipy
transcription, and the linear dashpot (damping=c, jaxdea.LinearViscous) unchanged bit for bit.

Every law and configuration runs through ``jaxdea.sweep(payload=...)`` and through
``scipy_reference.reference_metrics(force=f)`` (LSODA, rtol 1e-9) with the same protocol: 20
cycles from rest, the last 5 averaged, two frequencies (off resonance and near it). The Drag
laws share one pytree structure, so jaxdea compiles once per configuration.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxdea
import scipy_reference as ref
from conftest import CONFIG_DIR

MASS = 2e-3  # kg
FREQS = (30.0, 75.0)  # Hz
CYCLES, AVERAGE = 20, 5
RTOL_POWER = 5e-3
C, C2, FC = 0.1, 1.0, 0.02  # N s/m, N s^2/m^2, N

# law name -> (jaxdea law, the same force for scipy)
LAWS = {
    "linear": (jaxdea.Drag(MASS, linear=C), lambda v: C * v),
    "quadratic": (jaxdea.Drag(MASS, quadratic=C2), lambda v: C2 * v * abs(v)),
    "coulomb": (jaxdea.Drag(MASS, coulomb=FC), lambda v: FC * np.tanh(v / 1e-3)),
}
CONFIGS = ("scdea_ls", "dcdea_rr", "dcdea_ls")  # drive A

# sweep(mass=MASS, damping=0.1, freq=FREQS, cycles=20, average=5), drive A, computed with the
# code before payload laws existed (commit 20820f1): the linear path must not move one bit.
# P_in re-recorded when the returned charge became an exact split at the current's zero
# instead of a quadrature of min(i, 0) (issue 14): it moved by 3e-8 to 4.8e-6 relative.
LINEAR_BEFORE = {
    "scdea_ls": {
        "P_out": ('0x1.b1843f62a7f28p-10', '0x1.0a3394b389048p-9'),
        "P_in": ('0x1.900a90d0ca1fep-3', '0x1.dbc23814f5a1ep-2'),
        "P_in_signed": ('0x1.73c34c94acca3p-3', '0x1.cc8504cba69ddp-2'),
        "amplitude": ('0x1.cbad16e1069acp-12', '0x1.c55874fc5a0d4p-12'),
        "v_rms": ('0x1.075e2f31241a9p-3', '0x1.23dd21cf2ffbfp-3'),
    },
    "dcdea_rr": {
        "P_out": ('0x1.921e4824fcb5ep-14', '0x1.6117323a48f84p-8'),
        "P_in": ('0x1.73499e2425ff0p-3', '0x1.e446399a312f2p-2'),
        "P_in_signed": ('0x1.6ac718c6a3452p-3', '0x1.dfa6cc4940b5ep-2'),
        "amplitude": ('0x1.91a6d34de8958p-13', '0x1.6ec3eb4ef1f6cp-11'),
        "v_rms": ('0x1.fb4d68c2f958ap-6', '0x1.db5f15a03e6f0p-3'),
    },
    "dcdea_ls": {
        "P_out": ('0x1.93f4eab207896p-14', '0x1.bb26649cca2c0p-9'),
        "P_in": ('0x1.7775ff2c2c46fp-3', '0x1.d42515223f6c2p-2'),
        "P_in_signed": ('0x1.6bf596a8fff49p-3', '0x1.d2ddf6c96676ep-2'),
        "amplitude": ('0x1.6c3b309565508p-13', '0x1.217aa579f3906p-11'),
        "v_rms": ('0x1.fc75f0fbb1df6p-6', '0x1.7892f2dd4ce5fp-3'),
    },
}


def _rel(a, b):
    return abs(a - b) / abs(b)


def _compare(cfg, label, ds, mass, force, position_force, worst, failures):
    """The sweep ``ds`` (at FREQS) against the scipy reference with the same payload forces:
    the largest relative errors go to ``worst``, the ones above RTOL_POWER to ``failures``."""
    for i, f in enumerate(FREQS):
        r = ref.reference_metrics(cfg, mass, 0.0, f, cycles=CYCLES, average=AVERAGE, rtol=1e-9,
                                  method="LSODA", force=force, position_force=position_force)
        assert r["P_out"] >= 0.0
        for name in ("P_out", "P_in"):
            got = float(ds[name].values[i])
            err = _rel(got, r[name])
            worst[(label, name)] = max(worst.get((label, name), 0.0), err)
            if not err <= RTOL_POWER:
                failures.append(f"{label} {name} at {f:g} Hz: jaxdea {got:.6g} vs "
                                f"scipy {r[name]:.6g} (rel err {err:.3%})")


@pytest.mark.parametrize("cfg", CONFIGS)
def test_drag_laws_match_scipy_reference(models, cfg):
    worst = {}
    failures = []
    p_out = {}
    for law_name, (law, force) in LAWS.items():
        ds = jaxdea.sweep(models[cfg], payload=law, freq=list(FREQS), cycles=CYCLES,
                          average=AVERAGE)
        assert np.all(ds.status.values == 0)
        assert np.all(ds.P_out.values >= 0.0), (law_name, ds.P_out.values)
        assert ds.attrs["payload"] == "Drag" and ds.attrs["mass"] == MASS
        p_out[law_name] = ds.P_out.values
        _compare(cfg, law_name, ds, MASS, force, None, worst, failures)
    print(f"\n[{cfg}] max rel err: "
          + ", ".join(f"{law} {name} {v:.2e}" for (law, name), v in worst.items()))
    assert not failures, "; ".join(failures)
    # Drag(linear=c) is the linear dashpot: same P_out as damping=c (LINEAR_BEFORE)
    before = np.array([float.fromhex(x) for x in LINEAR_BEFORE[cfg]["P_out"]])
    np.testing.assert_allclose(p_out["linear"], before, rtol=1e-12, atol=0)


@pytest.mark.parametrize("cfg", CONFIGS)
def test_linear_viscous_unchanged(models, cfg):
    """damping=c and payload=LinearViscous(M, c) are one code path (bit-identical to each
    other) and give the pre-payload-law numbers (LINEAR_BEFORE, recorded on this project's
    machines from the unchanged code, where they matched bit for bit; compared here to 1e-12
    so that another CPU or XLA build's last bits do not fail it)."""
    expected = {k: np.array([float.fromhex(x) for x in v])
                for k, v in LINEAR_BEFORE[cfg].items()}
    runs = [jaxdea.sweep(models[cfg], freq=list(FREQS), cycles=CYCLES, average=AVERAGE,
                         **kwargs)
            for kwargs in ({"mass": MASS, "damping": C},
                           {"payload": jaxdea.LinearViscous(mass=MASS, damping=C)})]
    for name, values in expected.items():
        assert np.array_equal(runs[0][name].values, runs[1][name].values), (cfg, name)
        np.testing.assert_allclose(runs[0][name].values, values, rtol=1e-12, atol=0,
                                   err_msg=f"{cfg} {name}")
    ds = runs[1]
    assert ds.attrs["payload"] == "LinearViscous" and ds.attrs["payload_damping"] == C


def test_coulomb_smoothing_effect(models):
    """The tanh smoothing of the Coulomb term: v_s = 1e-3 vs 1e-4 m/s moves P_out by < 0.5 %
    (the number quoted in the jaxdea.Drag docstring)."""
    out = []
    for vs in (1e-3, 1e-4):
        ds = jaxdea.sweep(models["scdea_ls"], payload=jaxdea.Drag(MASS, coulomb=FC,
                                                                  coulomb_velocity=vs),
                          freq=list(FREQS), cycles=CYCLES, average=AVERAGE)
        out.append(ds.P_out.values)
    change = np.abs(out[1] - out[0]) / out[1]
    print(f"\nCoulomb smoothing: P_out {out[0]} (v_s=1e-3) vs {out[1]} (v_s=1e-4), "
          f"rel change {change}")
    assert np.all(change < 5e-3), change


@pytest.mark.parametrize("kwargs, match", [
    ({"payload": jaxdea.Drag(MASS, quadratic=-1.0)}, "payload.quadratic must be >= 0"),
    ({"payload": jaxdea.Drag(MASS, coulomb=float("nan"))}, "payload.coulomb must be finite"),
    ({"payload": jaxdea.Drag(MASS, coulomb=0.1, coulomb_velocity=0.0)},
     "payload.coulomb_velocity must be > 0"),
    ({"payload": jaxdea.Drag(-1e-3, linear=0.1)}, "payload.mass must be >= 0"),
    ({"payload": jaxdea.Drag(MASS, linear=[0.1, 0.2])}, "payload.linear must be a scalar"),
    ({"payload": jaxdea.Drag(MASS, linear=0.1), "damping": 0.1}, "not both"),
    ({"payload": jaxdea.Drag(MASS, linear=0.1), "mass": 1e-3}, "differs from payload.mass"),
    ({"payload": "drag"}, "payload must be a payload law"),
    ({"mass": MASS}, "damping is missing"),
    ({"damping": 0.1}, "mass is missing"),
])
def test_payload_validation(models, kwargs, match):
    with pytest.raises(jaxdea.SweepError, match=match):
        jaxdea.sweep(models["scdea_ls"], freq=[50.0], cycles=2, average=1, **kwargs)


def test_make_loadings_payload(models):
    law = jaxdea.Drag(MASS, quadratic=C2, coulomb=FC)
    loading = jaxdea.make_loadings(models["dcdea_ls"], None, None, [10.0, 20.0, 30.0],
                                   payload=law)
    assert isinstance(loading.payload, jaxdea.Drag)
    np.testing.assert_array_equal(loading.payload.mass, [MASS] * 3)
    np.testing.assert_array_equal(loading.payload.quadratic, [C2] * 3)
    v = np.array([-0.3, 0.0, 0.2])
    np.testing.assert_allclose(law.dissipated_power(v), law.resisting_force(v) * v)
    assert np.all(np.asarray(law.dissipated_power(np.linspace(-1, 1, 11))) >= 0.0)


def test_simulate_takes_a_payload_law(models):
    kw = dict(freq=75.0, cycles=2, points_per_cycle=50)
    a = jaxdea.simulate(models["scdea_ls"], mass=MASS, damping=C, **kw)
    b = jaxdea.simulate(models["scdea_ls"], payload=jaxdea.Drag(MASS, linear=C), **kw)
    np.testing.assert_allclose(b.payload_position, a.payload_position, rtol=0, atol=1e-15)
    assert b.attrs["payload"] == "Drag" and a.attrs["damping"] == C
    with pytest.raises(jaxdea.SweepError, match="not both"):
        jaxdea.simulate(models["scdea_ls"], damping=C, payload=jaxdea.Drag(MASS), **kw)


# Loads that push on the disk at rest: a preloaded spring to ground, a weight. Each is summed
# with a linear dashpot (the power goes somewhere); the scipy side gets the same forces as
# f(v) (dissipative) + g(x) (conservative, x = the payload dof's signed deflection).
K_P, PRELOAD = 300.0, 0.05  # N/m, N
HEAVY = 20e-3  # kg: a weight of 0.196 N moves P_out by a few % (2 g: ~1 %)
G = 9.80665


def _anchor(cfg):
    eq = ref.static_equilibrium(cfg)
    return eq["d"] if cfg == "scdea_ls" else eq["d_B"]


def _loaded_cases(cfg):
    """(label, jaxdea law, mass, scipy f(v), scipy g(x)) of the loaded payloads."""
    xa = _anchor(cfg)
    cases = [("elastic", jaxdea.Drag(MASS, linear=C) + jaxdea.Elastic(
        stiffness=K_P, preload=PRELOAD), MASS, lambda v: C * v,
        lambda x: PRELOAD + K_P * (x - xa))]
    for tilt in (0.0, np.pi):  # payload hanging below the actuator / sitting on top
        cases.append((f"gravity tilt={tilt:.3g}", jaxdea.Drag(HEAVY, linear=C) + jaxdea.Gravity(
            tilt=tilt), HEAVY, lambda v: C * v,
            lambda x, t=tilt: -HEAVY * G * np.cos(t)))
    return cases


@pytest.mark.parametrize("cfg", CONFIGS)
def test_loaded_payloads_match_scipy_reference(models, cfg):
    """Elastic and Gravity loads (rest state solved with them on) against scipy, within 0.5 %
    on P_out and P_in; springs and weights are not output power (P_out = mean c v^2)."""
    failures, worst = [], {}
    moved = []
    for label, law, mass, force, position_force in _loaded_cases(cfg):
        # the rest state with the load on: jaxdea's Newton against scipy's fsolve
        eq = ref.static_equilibrium(cfg, position_force=position_force)
        rest = np.asarray(models[cfg].actuator.initial_state(
            jaxdea.payloads.anchored(law, _anchor(cfg))).q)
        want = [eq["d"]] if cfg == "scdea_ls" else (
            [eq["d_B"]] if cfg == "dcdea_rr" else [eq["d_A"], eq["d_B"]])
        np.testing.assert_allclose(rest, want, rtol=1e-9, atol=1e-14, err_msg=label)
        moved.append(abs(rest[-1] - _anchor(cfg)))
        ds = jaxdea.sweep(models[cfg], payload=law, freq=list(FREQS), cycles=CYCLES,
                          average=AVERAGE)
        assert np.all(ds.status.values == 0), label
        assert np.all(ds.P_out.values > 0.0), (label, ds.P_out.values)
        _compare(cfg, label, ds, mass, force, position_force, worst, failures)
    print(f"\n[{cfg}] max rel err: "
          + ", ".join(f"{law} {name} {v:.2e}" for (law, name), v in worst.items()))
    assert not failures, "; ".join(failures)
    assert min(moved) > 1e-6, moved  # every load moved the rest state (the test can fail)


def test_conservative_laws_dissipate_nothing():
    """Springs and weights return what they store: no output power; the forces add."""
    v = np.linspace(-1.0, 1.0, 7)
    law = jaxdea.Drag(MASS, linear=C) + jaxdea.Elastic(stiffness=K_P, preload=PRELOAD,
                                                        anchor=0.004) + jaxdea.Gravity(tilt=0.5)
    np.testing.assert_allclose(law.dissipated_power(v), C * v * v, rtol=1e-15)
    np.testing.assert_allclose(law.force(0.005, v),
                               C * v + PRELOAD + K_P * 0.001 - MASS * G * np.cos(0.5),
                               rtol=1e-14)
    assert law.mass == MASS and law.loads_at_rest and not jaxdea.Drag(MASS).loads_at_rest
    with pytest.raises(ValueError, match="at most one law of each type"):
        jaxdea.Drag(MASS) + jaxdea.Drag(MASS)


def test_too_heavy_a_payload_is_refused(models):
    """A weight the actuator cannot hold: one clear line before any compute."""
    with pytest.raises(jaxdea.SweepError, match="no static equilibrium with this payload"):
        jaxdea.sweep(models["scdea_ls"], payload=jaxdea.Drag(10.0, linear=C) + jaxdea.Gravity(),
                     freq=[50.0], cycles=2, average=1)


def test_powermap_over_a_law_parameter(models):
    """A payload parameter given as an axis is the map's second dim; every cell equals the
    sweep of the same payload (the map and the sweep share the engine)."""
    law = jaxdea.Drag(0.0, linear=C) + jaxdea.Gravity(tilt=[0.0, np.pi])
    mass = [MASS, HEAVY]
    ds = jaxdea.powermap(models["scdea_ls"], mass=mass, payload=law, freq=list(FREQS),
                         cycles=CYCLES, average=AVERAGE, progress=False)
    assert ds["P_out"].dims == ("M", "tilt", "f") and ds["tilt"].attrs["units"] == "rad"
    assert ds.attrs["payload"] == "Drag + Gravity" and ds.attrs["payload_linear"] == C
    assert "not output power" in ds.attrs["P_out_meaning"]
    for i, m in enumerate(mass):
        for j, tilt in enumerate((0.0, np.pi)):
            sw = jaxdea.sweep(models["scdea_ls"], payload=jaxdea.Drag(m, linear=C)
                              + jaxdea.Gravity(tilt=tilt), freq=list(FREQS), cycles=CYCLES,
                              average=AVERAGE)
            np.testing.assert_allclose(ds["P_out"].values[i, j], sw["P_out"].values,
                                       rtol=1e-12, atol=0)
    # the weight of the heavy payload moves P_out (hanging vs on top): the axis is live
    assert abs(ds["P_out"].values[1, 0, 1] / ds["P_out"].values[1, 1, 1] - 1) > 1e-2
    with pytest.raises(jaxdea.SweepError, match="needs one law parameter as a 1-D axis"):
        jaxdea.powermap(models["scdea_ls"], mass=mass, payload=jaxdea.Drag(0.0, linear=C),
                        freq=[50.0], cycles=2, average=1, progress=False)
    with pytest.raises(jaxdea.SweepError, match="at most one law parameter may be an axis"):
        jaxdea.powermap(models["scdea_ls"], mass=mass, freq=[50.0], cycles=2, average=1,
                        payload=jaxdea.Drag(0.0, linear=[0.1, 1.0], quadratic=[1.0, 2.0]),
                        progress=False)
    with pytest.raises(jaxdea.SweepError, match="no static equilibrium"):
        jaxdea.powermap(models["scdea_ls"], mass=[MASS, 10.0], freq=[50.0], cycles=2,
                        average=1, payload=law, progress=False)


def test_payload_table_in_configs(tmp_path):
    """The [payload] table: read by load_payload, checked by load_config (one line naming
    the key and its range)."""
    law = jaxdea.load_payload(CONFIG_DIR / "scdea_ls_loaded.toml")
    assert [type(x).__name__ for x in law.laws] == ["Drag", "Elastic", "Gravity"]
    assert law.mass == MASS and jaxdea.payloads.parameters(law)["stiffness"] == 200.0
    assert jaxdea.load_payload(CONFIG_DIR / "scdea_ls.toml") is None
    text = (CONFIG_DIR / "scdea_ls_loaded.toml").read_text()
    for old, new, match in (("tilt = 0.0", "tilt = nan", "payload.gravity.tilt"),
                            ("stiffness = 200.0", "stiffnes = 200.0",
                             r"missing key\(s\) in \[payload.elastic\]: stiffness"),
                            ("tilt = 0.0", "tilt = 0.0\nangle = 1.0",
                             r"unknown key\(s\) in \[payload.gravity\]: angle"),
                            ("mass = 2e-3", "mass = -1.0", r"payload.mass = -1.0 is outside")):
        bad = tmp_path / "bad.toml"
        bad.write_text(text.replace(old, new))
        with pytest.raises(jaxdea.ConfigError, match=match):
            jaxdea.load_config(bad)


def test_cli_payload_flags(tmp_path, capsys):
    """The CLI's law flags and the config's table give the same sweep as the Python API."""
    from jaxdea.cli import main

    cfg = str(CONFIG_DIR / "scdea_ls.toml")
    out = tmp_path / "s.nc"
    rc = main(["sweep", cfg, "--mass", str(HEAVY), "--damping", str(C), "--tilt", "0",
               "--freq", "75:75:1", "--cycles", str(CYCLES), "--average", str(AVERAGE),
               "--out", str(out)])
    assert rc == 0 and "Drag + Gravity" in capsys.readouterr().out
    import xarray as xr

    with xr.open_dataset(out, engine="h5netcdf") as ds:
        got = float(ds["P_out"].values[0])
    want = jaxdea.sweep(jaxdea.load_config(cfg), payload=jaxdea.Drag(HEAVY, linear=C)
                        + jaxdea.Gravity(tilt=0.0), freq=[75.0], cycles=CYCLES,
                        average=AVERAGE)["P_out"].values[0]
    assert got == pytest.approx(want, rel=1e-12)
    assert main(["sweep", cfg, "--mass", "2e-3", "--freq", "75:75:1", "--out",
                 str(tmp_path / "x.nc")]) == 2
    assert "--damping is missing" in capsys.readouterr().err
