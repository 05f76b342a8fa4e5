"""Rotational double-cone DEA (paper 003): paper numbers, static vs dynamic steady state,
symmetry, autodiff Jacobian, IFT gradients, design optimisation, config validation, CLI.

Compiled functions are shared through module fixtures (one study kernel on the full Fig-12
grid, one equilibrium solver, one diffrax integrator, one value-and-grad objective).
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.config import ConfigError, model_from_dict
from jaxdea.materials import ogden_type_stress
from jaxdea.models import rotary as R
from jaxdea.studies import rotary as RS

CONFIG = Path(__file__).parents[1] / "configs" / "rotary_dcdea.toml"
RI = np.linspace(2e-3, 7e-3, 26)  # Fig 12 grid: 0.2 mm steps
D = np.linspace(4e-3, 18e-3, 57)  # 0.25 mm steps


def raw() -> dict:
    with CONFIG.open("rb") as fh:
        return tomllib.load(fh)


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


@pytest.fixture(scope="module")
def study(model):
    return jaxdea.rotary_study(model, RI, D)  # the whole Fig-12 grid: ONE vmapped call


def _at(ds, ri, d):
    return ds.sel(ri=ri, d=d, method="nearest")


# ---- paper numbers -------------------------------------------------------------------------


@pytest.mark.parametrize("d, expected", [(4e-3, 6.35), (7e-3, 9.80), (10e-3, 8.80)])
def test_optimised_prototypes_match_paper_model(study, d, expected):
    cell = _at(study, 2e-3, d)
    assert float(cell.ri) == pytest.approx(2e-3) and float(cell.d) == pytest.approx(d)
    assert int(cell.status) == 0
    assert float(cell.theta_deg) == pytest.approx(expected, abs=0.1)


def test_first_prototype_angle(model):
    sol = R.equilibrium(model.with_geometry(8.5e-3, 9e-3))
    assert int(sol.status) == 0
    assert np.degrees(float(sol.q[2])) == pytest.approx(2.0, abs=0.2)  # paper: 2.2 measured


def test_fig12_trends(study):
    th = study["theta_deg"].values
    assert study["theta_deg"].dims == ("ri", "d") and th.shape == (26, 57)
    assert study["ri"].attrs["units"] == "m" and study["d"].attrs["units"] == "m"
    assert (study["status"].values == 0).all() and np.isfinite(th).all()
    # smaller inner radius -> larger angle at every d (paper: "reducing r_i")
    assert (np.diff(th, axis=0) < 0).all()
    # at r_i = 2 mm the angle peaks inside the d range, near 7-8 mm (paper: d = 7 mm)
    j = int(np.argmax(th[0]))
    assert 6.5e-3 <= D[j] <= 8.5e-3 and 9.8 < th[0, j] < 10.3
    # every active element sees E_max at q = 0 (eq 30 with the frozen eq 9)
    lam0 = study["rest_stretch"].values
    assert np.allclose(study["voltage"].values * lam0 / 50e-6, 80e6)


def test_literal_field_reading_gives_larger_angle(model):
    lit = R.equilibrium(model.with_field("literal"))
    fro = R.equilibrium(model)
    assert np.degrees(float(lit.q[2])) == pytest.approx(11.2, abs=0.1)  # reference/rotary.md
    assert np.degrees(float(fro.q[2])) == pytest.approx(9.8, abs=0.1)


# ---- structure: symmetry, Jacobian, constitutive law ----------------------------------------


def test_diagonal_pairs_give_mirror_images(model):
    grav = R.paper_model(2e-3, 7e-3, gravity=9.807)  # gravity keeps the mirror (x -> -x)
    bc = R.equilibrium(grav.with_pattern([0, 1, 1, 0]))
    ad = R.equilibrium(grav.with_pattern([1, 0, 0, 1]))
    assert int(bc.status) == 0 and int(ad.status) == 0
    assert float(bc.q[2]) > 0.1 and float(ad.q[2]) < -0.1  # B+C counter-clockwise
    np.testing.assert_allclose(ad.q[2], -bc.q[2], rtol=1e-10)
    np.testing.assert_allclose(ad.q[0], -bc.q[0], atol=1e-12)
    np.testing.assert_allclose(ad.q[1], bc.q[1], rtol=1e-9)
    assert float(bc.q[1]) < -1e-5  # the spacer sags under gravity


def test_jacobian_matches_finite_differences(model):
    rng = np.random.default_rng(0)
    lengths = jax.jit(lambda q: model.lengths(q))
    jacobian = jax.jit(lambda q: model.jacobian(q))
    for _ in range(3):
        q = jnp.asarray(rng.normal(size=3) * np.array([1e-3, 1e-3, 0.2]))
        jac = np.asarray(jacobian(q))
        fd = np.zeros((4, 3))
        for k, h in enumerate((1e-7, 1e-7, 1e-6)):
            e = np.zeros(3)
            e[k] = h
            fd[:, k] = (np.asarray(lengths(q + e)) - np.asarray(lengths(q - e))) / (2 * h)
        np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-9)
    # at q = 0 every element is a cone generator of slope (d + f - h) / (r_o - r_i)
    j0 = np.asarray(jacobian(jnp.zeros(3)))
    lam0 = float(model.rest_stretch())
    np.testing.assert_allclose(np.abs(j0[:, 0]), 1 / lam0, rtol=1e-12)


def test_generalized_forces_are_virtual_work(model):
    q = jnp.array([2e-4, -1e-4, 0.05])
    v = model.voltages()
    tau, f = jax.jit(lambda q: (model.generalized_forces(q, jnp.zeros(3), v),
                                model.element_forces(q, jnp.zeros(3), v)))(q)
    tau, f = np.asarray(tau), np.asarray(f)
    # eq 25: f . dl + tau . dq = 0 for any small displacement dq
    dq = np.array([1e-8, 2e-8, 1e-6])
    lengths = jax.jit(lambda q: model.lengths(q))
    dl = np.asarray(lengths(q + dq / 2)) - np.asarray(lengths(q - dq / 2))
    assert abs(f @ dl + tau @ dq) < 1e-6 * np.abs(f @ dl)


def test_ogden_type_law():
    lam = jnp.array([1.0, 1.1, 1.3])
    a, b, g = (2.0, 4.0), jnp.array([1.707e6, -0.023e6]), jnp.array([1.298e6, -0.955e6])
    s_tuple = ogden_type_stress(lam, 0.0, 0.0, a, b, g, 0.0, 0.0)
    s_array = ogden_type_stress(lam, 0.0, 0.0, jnp.array(a), b, g, 0.0, 0.0)
    np.testing.assert_allclose(s_tuple, s_array, rtol=1e-13)
    assert float(s_tuple[0]) == pytest.approx(1.707e6 - 1.298e6 - 0.023e6 + 0.955e6)
    # electrostatic and viscous terms of eq 10
    eps = 8.854e-12 * 2.8
    s = ogden_type_stress(1.0, 0.5, 80e6, a, b, g, eps, 0.2e6)
    assert float(s - s_tuple[0]) == pytest.approx(-eps * 80e6**2 + 0.1e6)


# ---- steady state: static vs dynamic, stability codes -------------------------------------


def test_static_equilibrium_equals_time_integration_to_rest():
    grav = R.paper_model(2e-3, 7e-3, gravity=9.807)
    static = R.equilibrium(grav)
    rest = RS.settle(grav)  # filtered step, diffrax to rest
    assert int(static.status) == 0 and float(rest.t) > 0.5
    assert abs(float(rest.q[2] - static.q[2])) < 1e-6
    np.testing.assert_allclose(rest.q[:2], static.q[:2], atol=1e-9)


def test_filtered_step_response_is_overdamped_rise(model):
    ds = RS.simulate_rotary(model, t_end=1.0)
    th = ds["theta_deg"].values
    final = np.degrees(float(R.equilibrium(model).q[2]))
    # starts at the unactuated equilibrium, theta = 0 by symmetry (a Newton solve: exactly 0
    # with XLA's 256-bit vectors, 1.5e-14 deg with 512-bit ones), then rises monotonically
    assert abs(th[0]) <= 1e-9 and np.all(np.diff(th) >= -1e-9)  # (heavily damped)
    assert th.max() <= final + 1e-6 and th[-1] > 0.9 * final
    v = ds["voltage"].values
    assert np.all(v[:, [0, 3]] == 0) and v[-1, 1] == pytest.approx(float(model.voltage_max()),
                                                                   rel=1e-6)


def test_no_stable_equilibrium_and_invalid_geometry_get_status_codes(model):
    overdriven = R.equilibrium(model.with_pattern([0, 2, 2, 0]))
    assert int(overdriven.status) == R.UNSTABLE and np.isnan(float(overdriven.q[2]))
    assert float(overdriven.min_eig) < 0
    flat = R.equilibrium(model.with_geometry(d=1.5e-3))  # d + f < h: inverted cone
    assert int(flat.status) == R.INVALID and np.isnan(float(flat.q[2]))
    fine = R.equilibrium(model.with_pattern([0, 1.5, 1.5, 0]))  # still below the fold
    assert int(fine.status) == R.OK and float(fine.min_eig) > 0


# ---- gradients and design optimisation ----------------------------------------------------


def test_angle_gradient_matches_central_differences(model):
    fun = RS.angle_objective  # (model, [r_i, d]) -> (-|theta| deg, gradient), jitted
    x = jnp.array([4e-3, 10e-3])
    val, grad = fun(model, x)
    assert float(val) == pytest.approx(-4.7365, abs=1e-3)
    for k in range(2):
        h = 1e-7
        fp = float(fun(model, x.at[k].add(h))[0])
        fm = float(fun(model, x.at[k].add(-h))[0])
        fd = (fp - fm) / (2 * h)
        assert abs(float(grad[k]) - fd) <= 1e-4 * abs(fd)
    assert float(grad[0]) > 0 and float(grad[1]) > 0  # angle grows as r_i and d shrink here


@pytest.mark.parametrize("start", [(4e-3, 12e-3), (6.5e-3, 5e-3), (3e-3, 17e-3)])
def test_optimiser_reaches_grid_optimum(model, study, start):
    best = float(study["theta_deg"].max())
    res = RS.optimise_design(model, start=start)
    assert res["theta_deg"] >= best - 1e-9
    assert res["r_i"] == pytest.approx(2e-3)  # lower bound: smaller r_i is better
    assert 7e-3 < res["d"] < 8.5e-3


# ---- config ---------------------------------------------------------------------------------


def test_config_loads(model):
    assert isinstance(model, jaxdea.RotaryDCDEA) and model.field == "frozen"
    assert float(model.r_o) == 22.5e-3 and model.material.alpha == (2.0, 4.0)
    assert model.pattern.dtype == np.float64


def _set(cfg, path, value):
    *head, last = path.split(".")
    node = cfg
    for k in head:
        node = node[k]
    if value is None:
        del node[last]
    else:
        node[last] = value
    return cfg


@pytest.mark.parametrize(
    "path, value, expected",
    [
        ("geometry.inner_radius", 22.5e-3, r"geometry\.inner_radius = 0\.0225 .*\(0, 0\.0225\) m"),
        ("geometry.inner_radius", 30e-3, r"geometry\.inner_radius .*allowed range \(0, 0\.0225\)"),
        ("geometry.spacer_half_length", 2e-3,
         r"geometry\.spacer_half_length = 0\.002 .*\(0\.002, inf\) m"),
        ("geometry.spacer_half_length", 1e-3, r"geometry\.spacer_half_length .*flat or inverted"),
        ("geometry.thickness", 0.0, r"geometry\.thickness = 0\.0 .*\(0, inf\) m"),
        ("geometry.thickness", -5e-5, r"geometry\.thickness"),
        ("geometry.inner_radius", -1e-3, r"geometry\.inner_radius = -0\.001 .*\(0, inf\)"),
        ("spacer.mass", 0.0, r"spacer\.mass = 0\.0 .*\(0, inf\) kg"),
        ("material.eta_v0", -1.0, r"material\.eta_v0 = -1\.0 .*\[0, inf\) Pa s"),
        ("material.beta", [1.7e6, "x"], r"material\.beta\[1\]"),
        ("material.gamma", [1.3e6], r"same number of terms"),
        ("drive.pattern", [1.0, 0.0, 1.0], r"drive\.pattern must have 4 entries"),
        ("drive.pattern", [0.0, -1.0, 1.0, 0.0], r"drive\.pattern\[1\] = -1\.0 .*\[0, inf\)"),
        ("field", "bogus", r"field = 'bogus' is not one of frozen, literal"),
        ("geometry.bogus", 1.0, r"unknown key\(s\) in \[geometry\]: bogus"),
        ("spacer.inertia", None, r"missing key\(s\) in \[spacer\]: inertia \(allowed range"),
    ],
)
def test_config_errors_name_field_and_range(path, value, expected):
    cfg = _set(copy.deepcopy(raw()), path, value)
    with pytest.raises(ConfigError, match=expected):
        model_from_dict(cfg)


# ---- CLI --------------------------------------------------------------------------------


def test_cli_rotary_study(tmp_path, study, capsys):
    import xarray as xr

    from jaxdea.cli import main

    out, png = tmp_path / "study.nc", tmp_path / "study.png"
    rc = main(["rotary-study", str(CONFIG), "--ri", "2e-3:7e-3:26", "--d", "4e-3:18e-3:57",
               "--out", str(out), "--plot", str(png)])
    assert rc == 0 and png.stat().st_size > 10_000
    ds = xr.open_dataset(out, engine="h5netcdf")
    np.testing.assert_allclose(ds["theta_deg"].values, study["theta_deg"].values, rtol=1e-12)
    np.testing.assert_allclose(ds["ri"].values, RI)  # linear spacing by default
    assert "max theta" in capsys.readouterr().out
    assert main(["rotary-study", str(CONFIG), "--ri", "2e-3:7e-3:3", "--d", "4e-3:18e-3:5",
                 "--out", str(tmp_path / "x.txt")]) == 2
