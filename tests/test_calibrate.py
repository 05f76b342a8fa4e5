"""Calibration (issue 5): data loading/validation, parameter transforms and bounds, the fit
methods, divergence, the CLI, and recovery of known SCDEA-LS membrane parameters from a
synthetic noisy frequency response (problem b)."""

from __future__ import annotations

import functools
import math
import re
import tomllib
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.calibration import (
    CalibrationError,
    DataError,
    FrequencyResponse,
    TimeSeries,
    calibrate,
    error_metrics,
    frequency_response,
    get_params,
    load_data,
    make_params,
    parameter_names,
    resolve_names,
    save_data,
    set_params,
    write_fitted_config,
)
from jaxdea.cli import main

CONFIG = Path(__file__).parents[1] / "configs" / "scdea_ls.toml"


# ---- a cheap toy model for the machinery --------------------------------------------------


class Toy(eqx.Module):
    k: jax.Array
    c: jax.Array
    a: jax.Array
    shift: jax.Array


def toy_predict(m, d):
    t = jnp.asarray(d.t)
    return {"displacement": m.a * jnp.exp(-m.c * t) * jnp.sin(m.k * t) + m.shift}


def toy(k=5.0, c=0.3, a=2e-3, shift=0.0):
    return Toy(*(jnp.asarray(v, dtype=jnp.float64) for v in (k, c, a, shift)))


@pytest.fixture(scope="module")
def toy_data():
    t = np.linspace(0.0, 10.0, 300)
    zero = TimeSeries(t=t, voltage=0 * t, displacement=0 * t)
    y = np.asarray(toy_predict(toy(), zero)["displacement"])
    rng = np.random.default_rng(0)
    return TimeSeries(t=t, voltage=0 * t, displacement=y + 0.01 * np.ptp(y) *
                      rng.standard_normal(t.size))


TOY_BOUNDS = {"k": (1.0, 10.0), "c": (0.01, 3.0), "a": (1e-4, 1e-1)}


@pytest.mark.parametrize("method", ["lbfgs", "lm", "adam", "de"])
def test_toy_recovery_every_method(toy_data, method):
    start = toy(k=4.5, c=0.9, a=6e-3)  # c and a off by a factor of 3
    kw = dict(de_options=dict(popsize=30), maxiter=60) if method == "de" else {}
    res = calibrate(start, toy_data, ["k", "c", "a"], bounds=TOY_BOUNDS, method=method,
                    predict=toy_predict, seed=1, **kw)
    truth = {"k": 5.0, "c": 0.3, "a": 2e-3}
    for n, v in truth.items():
        assert abs(res.params[n] / v - 1) < 0.05, (method, n, res.params[n])
    assert res.e_rms < 2.0 and res.loss < 2e-4
    assert res.history[-1] <= res.history[0]
    assert float(res.model.shift) == 0.0  # unfitted parameters held
    assert set(res.std) == {"k", "c", "a"} and not res.flat
    if method == "de":
        assert res.n_evals == 30 * 61  # initial population + 60 generations, all counted


def test_flat_direction_is_reported(toy_data):
    """A parameter the data cannot see has no curvature: reported in ``flat``."""
    def predict(m, d):
        return toy_predict(eqx.tree_at(lambda t: t.shift, m, 0.0 * m.shift), d)

    res = calibrate(toy(k=4.8, c=0.35, a=2.5e-3, shift=1.0), toy_data, ["k", "c", "a", "shift"],
                    bounds={**TOY_BOUNDS, "shift": (0.1, 10.0)}, predict=predict)
    assert res.flat == ["shift"]
    assert math.isinf(res.rel_std["shift"]) and res.rel_std["k"] < 0.01
    assert "flat" in res.summary()


def test_auto_jacobian_mode_is_reverse_for_time_series(toy_data):
    """jac='auto' takes reverse mode for a time series (diffrax's checkpointed adjoint has no
    forward mode), for the gradient and for the curvature's residual Jacobian (jacrev); both
    equal forward mode's on a model that has both."""
    kw = dict(bounds=TOY_BOUNDS, predict=toy_predict, maxiter=3)
    start = toy(k=4.5, c=0.9, a=6e-3)
    auto = calibrate(start, toy_data, ["k", "c", "a"], **kw)
    fwd = calibrate(start, toy_data, ["k", "c", "a"], jac="fwd", **kw)
    assert "jacrev_z" in auto.objective._cache and "jac_z" not in auto.objective._cache
    np.testing.assert_allclose(auto.curvature, fwd.curvature, rtol=1e-8)
    for n in ("k", "c", "a"):
        assert auto.params[n] == pytest.approx(fwd.params[n], rel=1e-8)
    with pytest.raises(CalibrationError, match="jac = 'both' must be 'auto', 'fwd' or 'rev'"):
        calibrate(start, toy_data, ["k"], predict=toy_predict, jac="both")


def test_error_metrics_paper_definitions():
    zm = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    ze = zm + np.array([0.0, 0.1, -0.2, 0.0, 0.1])
    e_rms, e_m = error_metrics(ze, zm)
    assert e_m == pytest.approx(0.2 / 4.0 * 100)
    assert e_rms == pytest.approx(math.sqrt(0.06 / 5) / 4.0 * 100)


# ---- names, transforms, bounds ----------------------------------------------------------


def test_parameter_names_and_aliases(models):
    m = models["scdea_ls"]
    names = parameter_names(m)
    assert "actuator.membrane.dielectric.mu_A" in names and "voltage" in names
    assert resolve_names(m, "dielectric.tau,spring_stiffness") == [
        "actuator.membrane.dielectric.tau", "actuator.spring_stiffness"]
    m2 = set_params(m, {"dielectric.tau": 5e-3})
    assert get_params(m2, ["dielectric.tau"]) == {"actuator.membrane.dielectric.tau": 5e-3}
    assert float(m2.actuator.membrane.electrode.tau) == float(m.actuator.membrane.electrode.tau)


@pytest.mark.parametrize("fit, bounds, transforms, message", [
    (["mu_A"], None, None, "ambiguous"),
    (["nope"], None, None, "unknown parameter 'nope'"),
    (["dielectric.tau", "dielectric.tau"], None, None, "listed twice"),
    (["dielectric.tau"], {"dielectric.tau": (5e-3, 1e-3)}, None, "lower 0.005 >= upper 0.001"),
    (["dielectric.tau"], {"dielectric.tau": (1e-3, 1e-3)}, None, "impossible bounds"),
    (["dielectric.tau"], {"dielectric.tau": (0.0, 1.0)}, None,
     "non-positive lower bound 0 for the log-parameter actuator.membrane.dielectric.tau"),
    (["dielectric.tau"], {"dielectric.tau": (-1.0, 1.0)}, None, "non-positive lower bound"),
    (["dielectric.tau"], {"dielectric.tau": (1.0, 2.0)}, None, "outside its bounds"),
    (["dielectric.tau"], {"electrode.tau": (1e-4, 1.0)}, None, "which is not in fit"),
    (["dielectric.tau"], None, {"dielectric.tau": "sqrt"}, "allowed: log, linear"),
    ([], None, None, "fit is empty"),
])
def test_bad_fit_arguments_are_rejected(models, fit, bounds, transforms, message):
    with pytest.raises(CalibrationError, match=message.replace("(", r"\(")):
        make_params(models["scdea_ls"], fit, bounds, transforms)


def test_transforms_keep_parameters_inside_bounds(models):
    ps = make_params(models["scdea_ls"], ["dielectric.tau", "spring_stiffness", "duty"],
                     {"dielectric.tau": (1e-4, 1e-1), "duty": (0.1, 0.9)},
                     {"duty": "linear"})
    tau, k, duty = ps
    assert tau.log and k.log and not duty.log
    for z in (-50.0, -3.0, 0.0, 3.0, 50.0):
        assert 1e-4 * (1 - 1e-12) <= float(tau.theta_of_u(tau.u_of_z(z))) <= 1e-1 * (1 + 1e-12)
        assert float(k.theta_of_u(k.u_of_z(z))) > 0  # unbounded log: positive
        assert 0.1 <= float(duty.u_of_z(z)) <= 0.9
    for p in ps:  # z <-> theta round trip at the start
        z = p.z_of_u(float(p.u_of_theta(p.init)))
        assert float(p.theta_of_u(p.u_of_z(z))) == pytest.approx(p.init, rel=1e-9)


def test_de_needs_finite_bounds(toy_data):
    with pytest.raises(CalibrationError, match="finite bounds for c"):
        calibrate(toy(), toy_data, ["k", "c"], bounds={"k": (1, 10)}, method="de",
                  predict=toy_predict)


def test_bad_method_and_loss(toy_data):
    with pytest.raises(CalibrationError, match="method = 'bfgs'"):
        calibrate(toy(), toy_data, ["k"], method="bfgs", predict=toy_predict)
    with pytest.raises(CalibrationError, match="loss = 'l1'"):
        calibrate(toy(), toy_data, ["k"], loss="l1", predict=toy_predict)


# ---- divergence -------------------------------------------------------------------------


def test_adam_divergence_stops_with_message(toy_data):
    def blowup(m, d):  # optimum at the edge k = 6 of the finite region: Adam steps past it
        return {"displacement": jnp.sqrt(6.0 - m.k) * jnp.ones(d.t.shape)}

    with pytest.raises(CalibrationError, match=r"fit diverged \(adam.*loss = (nan|inf).*"
                                               r"lower learning_rate"):
        calibrate(toy(k=4.9), toy_data, ["k"], method="adam", learning_rate=1.0,
                  predict=blowup)


def test_lbfgs_divergence_stops_with_message(toy_data):
    def nan_off_start(m, d):
        y = toy_predict(m, d)["displacement"]
        return {"displacement": jnp.where(jnp.abs(m.k - 4.5) < 1e-12, y, jnp.nan)}

    with pytest.raises(CalibrationError, match="fit diverged.*lbfgs"):
        calibrate(toy(k=4.5), toy_data, ["k"], method="lbfgs", predict=nan_off_start)


def test_nan_at_start_is_a_clear_error(toy_data):
    def nan(m, d):
        return {"displacement": jnp.full(d.t.shape, jnp.nan) * m.k}

    with pytest.raises(CalibrationError, match="diverged.*at the start"):
        calibrate(toy(), toy_data, ["k"], method="lbfgs", predict=nan)


# ---- data files -------------------------------------------------------------------------


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_csv_units_are_converted(tmp_path):
    p = _write(tmp_path / "ts.csv", "t [ms],voltage [kV],displacement [mm]\n"
               "0,0,0\n10,1.5,0.2\n20,3,0.4\n")
    d = load_data(p)
    assert isinstance(d, TimeSeries)
    np.testing.assert_allclose(d.t, [0, 0.01, 0.02])
    np.testing.assert_allclose(d.voltage, [0, 1500, 3000])
    np.testing.assert_allclose(d.displacement, [0, 2e-4, 4e-4])
    p = _write(tmp_path / "fr.csv", "# mass = 2 g\n# damping = 0.1 N s/m\n"
               "f [Hz],P_out [mW],amplitude [mm]\n50,1.0,0.2\n60,2.0,0.3\n")
    d = load_data(p)
    assert isinstance(d, FrequencyResponse)
    np.testing.assert_allclose(d.mass, [2e-3, 2e-3])
    np.testing.assert_allclose(d.P_out, [1e-3, 2e-3])


@pytest.mark.parametrize("kind", ["csv", "nc"])
def test_save_load_round_trip(tmp_path, kind):
    f = np.array([30.0, 40.0, 30.0, 40.0])
    d = FrequencyResponse(f=f, mass=np.array([1e-3, 1e-3, 2e-3, 2e-3]), damping=0.1,
                          amplitude=np.array([1e-4, 2e-4, 3e-4, 4e-4]), P_out=f * 1e-5)
    back = load_data(save_data(d, tmp_path / f"fr.{kind}"))
    for k in ("f", "mass", "damping", "amplitude", "P_out"):
        np.testing.assert_allclose(getattr(back, k), getattr(d, k))
    assert len(back.groups()) == 2
    t = np.linspace(0, 1, 5)
    ts = TimeSeries(t=t, voltage=t * 1e3, displacement=t * 1e-3, force=t)
    back = load_data(save_data(ts, tmp_path / f"ts.{kind}"))
    np.testing.assert_allclose(back.force, t)


@pytest.mark.parametrize("text, message", [
    ("t [s],voltage [V]\n0,0\n1,1\n2,2\n", "missing column 'displacement'"),
    ("t [s],voltage [V],displacement [m]\n0,0,0\n2,1,1\n1,2,2\n",
     "'t' is not strictly increasing: row 2"),
    ("t [s],voltage [V],displacement [m]\n0,0,0\n1,nan,1\n2,2,2\n",
     "column 'voltage' has 1 non-finite value"),
    ("t [s],voltage [V],displacement [V]\n0,0,0\n1,1,1\n2,2,2\n",
     "column 'displacement' has unit 'V', which does not measure displacement"),
    ("t,voltage [V],displacement [m]\n0,0,0\n1,1,1\n2,2,2\n", "column 't' has no unit"),
    ("t [s],voltage [V],displacement [m],current [A]\n0,0,0,0\n1,1,1,1\n2,2,2,2\n",
     "unknown column 'current'"),
    ("t [s],voltage [V],displacement [m]\n0,0,0\n1,1\n2,2,2\n", "line 3 has 2 fields"),
    ("t [s],voltage [V],displacement [m]\n0,0,0\n1,x,1\n2,2,2\n", "'x' is not a number"),
    ("f [Hz],P_out [W]\n10,1\n20,2\n", "missing 'mass'"),
    ("# mass = 1 g\n# damping = 0.1 N s/m\nf [Hz]\n10\n20\n", "needs 'amplitude'"),
    ("# mass = 1 g\n# damping = 0.1 N s/m\nf [Hz],P_out [W]\n20,1\n10,2\n",
     "not strictly increasing"),
    ("# mass = 1 g\n# damping = 0.1 N s/m\nf [Hz],P_out [W]\n0,1\n10,2\n", "must be > 0 Hz"),
    ("voltage [V]\n1\n2\n", "need 't' (time series) or 'f'"),
])
def test_malformed_csv_is_rejected(tmp_path, text, message):
    p = _write(tmp_path / "bad.csv", text)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")) as e:
        load_data(p)
    assert "bad.csv" in str(e.value)


def test_malformed_netcdf_is_rejected(tmp_path):
    import xarray as xr

    t = np.linspace(0, 1, 5)
    ds = xr.Dataset({"t": ("t", t, {"units": "s"}), "voltage": ("t", t, {"units": "V"}),
                     "displacement": ("t", t)})
    ds.to_netcdf(tmp_path / "x.nc", engine="h5netcdf")
    with pytest.raises(DataError, match="'displacement' has no 'units'"):
        load_data(tmp_path / "x.nc")
    with pytest.raises(DataError, match="unknown data format '.txt'"):
        load_data(_write(tmp_path / "x.txt", "t [s]\n"))
    with pytest.raises(DataError, match="not found"):
        load_data(tmp_path / "missing.csv")


# ---- problem (b): SCDEA-LS frequency response -------------------------------------------

FIT_B = ["dielectric.mu_A", "dielectric.mu_B", "dielectric.tau", "dielectric.J_B"]
PREDICT_B = functools.partial(frequency_response, cycles=12, average=4)


def make_problem_b(fit=FIT_B, seed: int = 1):
    """3 payloads x 10 frequencies, P_out and amplitude, 1 % multiplicative Gaussian noise,
    generated by jaxdea (the same fixed-step protocol the fit uses) from configs/scdea_ls.toml;
    starts off by a factor of 3 (x3, /3, x3, /3) inside boxes of a decade either side.
    Returns ``(start, data, truth, bounds)`` (also used by bench/calibration_bench.py)."""
    true = jaxdea.load_config(CONFIG)
    f1 = np.linspace(30.0, 150.0, 10)
    f = np.tile(f1, 3)
    mass = np.repeat([1e-3, 4e-3, 16e-3], f1.size)
    shape = FrequencyResponse(f=f, mass=mass, damping=0.1, P_out=np.ones_like(f))
    clean = eqx.filter_jit(lambda m: PREDICT_B(m, shape))(true)
    rng = np.random.default_rng(seed)
    noisy = {k: np.asarray(v) * (1 + 0.01 * rng.standard_normal(f.size))
             for k, v in clean.items()}
    data = FrequencyResponse(f=f, mass=mass, damping=0.1, **noisy)
    truth = get_params(true, fit)
    start = set_params(true, {k: v * (3.0 if i % 2 == 0 else 1 / 3)
                              for i, (k, v) in enumerate(truth.items())})
    bounds = {k: (v / 10, v * 10) for k, v in truth.items()}
    return start, data, truth, bounds


@pytest.fixture(scope="module")
def problem_b():
    """The SCDEA-LS recovery problem (:func:`make_problem_b`) fitted by L-BFGS."""
    start, data, truth, bounds = make_problem_b()
    res = calibrate(start, data, FIT_B, bounds=bounds, method="lbfgs", loss="relative",
                    predict=PREDICT_B)
    print(res.summary())
    return dict(res=res, truth=truth, data=data)


def test_scdea_frequency_response_recovery(problem_b):
    res, truth = problem_b["res"], problem_b["truth"]
    for name in ("mu_A", "mu_B", "tau"):
        full = f"actuator.membrane.dielectric.{name}"
        err = res.params[full] / truth[full] - 1
        assert abs(err) < 0.05, (name, err)
        assert full not in res.flat
    assert res.e_rms < 2.0, res.metrics
    assert res.n_evals < 100


def test_scdea_gent_limit_of_the_branch_is_flat(problem_b):
    """J_B is not identified by a small-stroke frequency response: the Gauss-Newton curvature
    along it is ~1e-6 of that along mu_A, its 1-sigma exceeds 100 %, so the fit reports it in
    ``flat`` (and its value is not checked)."""
    res = problem_b["res"]
    jb = "actuator.membrane.dielectric.J_B"
    assert res.flat == [jb]
    h = np.diag(res.curvature)
    assert h[3] < 1e-5 * h[0]
    assert res.rel_std[jb] > 1.0


def test_fit_gradient_matches_finite_differences(problem_b):
    """The forward-mode gradient L-BFGS used, against central differences of the loss, at
    the start and at the optimum (z: the unconstrained fit variables).

    Steps of 1e-6: the loss is only piecewise smooth (the amplitude is the extremum of the
    samples, and its argmax moves from sample to sample as a parameter changes), and at the
    start point central differences of 1e-3 / 1e-4 / 1e-5 straddle such kinks: d/dmu_A
    69.500 / 69.499 / 69.481 against 69.4405 from both forward and reverse mode and from
    steps of 1e-6 (LawsonRK4's predictor: 70.353 / 70.328 / 70.2941 against 70.2941)."""
    obj = problem_b["res"].objective
    resid = obj.fn("resid_z")
    loss = lambda z: float(np.sum(np.asarray(resid(jnp.asarray(z))) ** 2))  # noqa: E731
    z_opt = np.array([p.z_of_u(math.log(v)) for p, v in
                      zip(obj.params, problem_b["res"].params.values())])
    for z in (obj.z0(), z_opt + 0.05):
        _, g = obj.value_and_grad(z, "fwd")
        for i in range(3):  # the identified parameters (J_B's gradient is ~0)
            e = np.zeros_like(z)
            e[i] = 1e-6
            fd = (loss(z + e) - loss(z - e)) / 2e-6
            assert fd == pytest.approx(g[i], rel=1e-4, abs=1e-9 * abs(g).max())


def test_frequency_response_agrees_with_sweep_engine(problem_b):
    """The fixed-step predictor and jaxdea.sweep's adaptive engine agree (same protocol)."""
    m = jaxdea.load_config(CONFIG)
    f = np.array([40.0, 80.0, 140.0])
    ds = jaxdea.sweep(m, mass=4e-3, damping=0.1, freq=f, cycles=12, average=4)
    d = FrequencyResponse.from_sweep(ds)
    pred = PREDICT_B(m, d)
    np.testing.assert_allclose(pred["P_out"], ds.P_out.values, rtol=0.02)
    np.testing.assert_allclose(pred["amplitude"], ds.amplitude.values, rtol=0.02)


# ---- CLI and fitted configs -------------------------------------------------------------


def test_fitted_config_round_trips(tmp_path):
    out = write_fitted_config(CONFIG, tmp_path / "fitted.toml",
                              {"actuator.membrane.dielectric.tau": 2.5e-3,
                               "actuator.spring_stiffness": 610.5}, header="a test")
    m = jaxdea.load_config(out)
    assert float(m.actuator.membrane.dielectric.tau) == 2.5e-3
    assert float(m.actuator.membrane.electrode.tau) == 1.5e-3
    assert float(m.actuator.spring_stiffness) == 610.5
    text = out.read_text()
    first, second = text.splitlines()[:2]  # jaxdea's mark (jaxdea.provenance), then the header
    assert first.startswith("# written by jaxdea") and second == "# a test"
    assert "# s, eta = mu_B * tau: chosen (fitted)" in text


def test_cli_calibrate_writes_loadable_config_and_plot(tmp_path, capsys):
    m = jaxdea.load_config(CONFIG)
    f = np.array([60.0, 80.0, 100.0])
    shape = FrequencyResponse(f=f, mass=2e-3, damping=0.1, P_out=np.ones_like(f))
    pred = PREDICT_B(m, shape)
    data = FrequencyResponse(f=f, mass=2e-3, damping=0.1, **{k: np.asarray(v) for k, v in
                                                            pred.items()})
    csv = save_data(data, tmp_path / "fr.csv")
    out, png = tmp_path / "fitted.toml", tmp_path / "fit.png"
    rc = main(["calibrate", str(CONFIG), "--data", str(csv), "--fit", "dielectric.tau",
               "--method", "de", "--popsize", "8", "--maxiter", "3", "--cycles", "12",
               "--average", "4", "--seed", "3", "--no-curvature", "--out", str(out),
               "--plot", str(png)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    # a progress bar over the generations (3 here) with the best loss, on stderr
    bar = captured.err.replace("\r", "\n")
    assert re.search(r"calibrate \(de\): +100%.* 3/3 .*loss \d", bar), bar[-500:]
    fitted = jaxdea.load_config(out)
    tau = float(fitted.actuator.membrane.dielectric.tau)
    assert 2e-4 <= tau <= 2e-2 and tau != 2e-3  # inside the default decade box, changed
    assert tomllib.loads(out.read_text())["membrane"]["dielectric"]["tau"] == tau
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert "e_rms" in captured.out


@pytest.mark.parametrize("args, message", [
    (["--fit", "mu_A"], "ambiguous"),
    (["--fit", "dielectric.tau", "--bounds", "dielectric.tau=0:1"], "non-positive lower"),
    (["--fit", "dielectric.tau", "--bounds", "dielectric.tau=1e-2:1e-3"], ">= upper"),
    (["--fit", "dielectric.tau", "--bounds", "tau"], "NAME=LO:HI"),
])
def test_cli_bad_arguments_fail_before_compute(tmp_path, capsys, args, message):
    csv = _write(tmp_path / "fr.csv", "# mass = 2 g\n# damping = 0.1 N s/m\n"
                 "f [Hz],P_out [mW]\n60,1\n80,2\n")
    rc = main(["calibrate", str(CONFIG), "--data", str(csv), "--out",
               str(tmp_path / "x.toml"), *args])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()


def test_cli_bad_data_file(tmp_path, capsys):
    csv = _write(tmp_path / "fr.csv", "f [Hz],P_out [V]\n60,1\n80,2\n")
    rc = main(["calibrate", str(CONFIG), "--data", str(csv), "--fit", "dielectric.tau",
               "--out", str(tmp_path / "x.toml")])
    assert rc == 2 and "does not measure P_out" in capsys.readouterr().err


def test_transient_predictor_checks_the_drive():
    from jaxdea.calibration import transient_predictor
    from jaxdea.signals import MultiSine

    sig = MultiSine(jnp.asarray([6e3, 6.5e3]), jnp.asarray([0.2, 0.4]))
    t = np.linspace(0.0, 7.5, 40)
    wrong = TimeSeries(t=t, voltage=np.full(t.size, 1e3), displacement=0 * t)
    with pytest.raises(DataError, match="differs from the drive signal"):
        transient_predictor(sig)(None, wrong)


def test_sweep_netcdf_loads_as_frequency_response(tmp_path):
    """A `jaxdea sweep` output file (f coordinate, payload in attrs) is calibration data."""
    import xarray as xr

    f = np.array([60.0, 70.0, 80.0])
    ds = xr.Dataset({"P_out": ("f", [1e-3, 2e-3, 3e-3], {"units": "W"}),
                     "amplitude": ("f", [1e-4, 2e-4, 3e-4], {"units": "m"}),
                     "P_in": ("f", [1.0, 1.0, 1.0], {"units": "W"})},
                    coords={"f": ("f", f, {"units": "Hz"})},
                    attrs={"mass": 2e-3, "damping": 0.1})
    ds.to_netcdf(tmp_path / "s.nc", engine="h5netcdf")
    d = load_data(tmp_path / "s.nc")
    assert isinstance(d, FrequencyResponse) and set(d.channels) == {"P_out", "amplitude"}
    np.testing.assert_allclose(d.mass, 2e-3)


def test_payload_law_parameter_recovery(models):
    """calibrate(payload=...) fits a payload law's parameter like a model's: the quadratic
    drag coefficient of a hanging payload is recovered from its own P_out (3 frequencies)."""
    from jaxdea.calibration.predictors import Loaded, frequency_response

    predict = functools.partial(frequency_response, cycles=10, average=2)
    rows = dict(f=np.array([40.0, 70.0, 100.0]), mass=np.full(3, 2e-3), damping=np.zeros(3))
    truth = jaxdea.Drag(0.0, linear=0.1, quadratic=2.0) + jaxdea.Gravity(tilt=0.0)
    p_out = predict(Loaded(models["scdea_ls"], truth),
                    FrequencyResponse(**rows, amplitude=np.ones(3)))["P_out"]
    data = FrequencyResponse(**rows, P_out=np.asarray(p_out))
    start = jaxdea.Drag(0.0, linear=0.1, quadratic=0.5) + jaxdea.Gravity(tilt=0.0)
    res = jaxdea.calibrate(models["scdea_ls"], data, ["payload.quadratic"], payload=start,
                           bounds={"payload.quadratic": (0.01, 100.0)}, predict=predict)
    assert res.params["payload.quadratic"] == pytest.approx(2.0, rel=1e-6)
    assert float(jaxdea.payloads.parameters(res.payload)["quadratic"]) == pytest.approx(2.0,
                                                                                        rel=1e-6)
    assert isinstance(res.model, jaxdea.Model)
    with pytest.raises(jaxdea.CalibrationError, match="unknown parameter"):
        jaxdea.calibrate(models["scdea_ls"], data, ["payload.cubic"], payload=start)


def test_cli_calibrate_fits_the_config_payload_law(tmp_path, capsys):
    """jaxdea calibrate with a config's [payload] table: --fit payload.quadratic recovers the
    load's drag coefficient and writes it back into the table, tagged fitted."""
    from jaxdea.calibration.predictors import Loaded

    cfg = Path(__file__).parents[1] / "configs" / "scdea_ls_loaded.toml"
    model, law = jaxdea.load_config(cfg), jaxdea.load_payload(cfg)
    truth = jaxdea.payloads.replace_parameters(law, quadratic=2.0).with_mass(0.0)
    f = np.array([40.0, 70.0, 100.0])
    rows = dict(f=f, mass=np.full(3, 2e-3), damping=np.zeros(3))
    pred = frequency_response(Loaded(model, truth), FrequencyResponse(**rows, P_out=np.ones(3)),
                              cycles=10, average=2)
    csv = save_data(FrequencyResponse(**rows, P_out=np.asarray(pred["P_out"])),
                    tmp_path / "fr.csv")
    out = tmp_path / "fitted.toml"
    rc = main(["calibrate", str(cfg), "--data", str(csv), "--fit", "payload.quadratic",
               "--cycles", "10", "--average", "2", "--no-curvature", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    fitted = tomllib.loads(out.read_text())["payload"]["quadratic"]
    assert fitted == pytest.approx(2.0, rel=1e-6)
    assert "quadratic = " in out.read_text() and "(fitted)" in out.read_text()
    assert float(jaxdea.payloads.parameters(jaxdea.load_payload(out))["quadratic"]) == fitted
    # a payload parameter the config's table does not hold cannot be written back
    rc = main(["calibrate", str(CONFIG), "--data", str(csv), "--fit", "payload.quadratic",
               "--quadratic", "1.0", "--out", str(tmp_path / "x.toml")])
    assert rc == 2 and "payload.quadratic" in capsys.readouterr().err
