"""Paper 004's clamped pure-shear DEA (jaxdea.actuators.planar): scipy reference, the paper's
observations (creep, hysteresis, peak lag), Model I vs II, gradients, config errors."""

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.config import ConfigError, model_from_dict
from jaxdea.models.planar import PlanarDEA
from jaxdea.signals import voltage_pattern
from jaxdea.studies.transient import displacement, hysteresis_area, solve
from viscoelastic_reference import planar_reference, vp1

CONFIGS = Path(__file__).parents[1] / "configs"
PEAK, PERIOD, CYCLES, PTS = 4500.0, 10.0, 12, 200  # reference drive: VP1, 4.5 kV, 10 s
TS = np.linspace(0.0, CYCLES * PERIOD, CYCLES * PTS + 1)


def _padded(model: PlanarDEA, n: int = 4) -> PlanarDEA:
    """Same model with inert extra units (mu = 1e-9 Pa, 1e-14 of the others), so Model I/II
    reuse the compiled 4-unit solve."""
    m = model.material
    k = n - m.mu.shape[0]
    pad = lambda a, v: jnp.concatenate([a, jnp.full(k, v)])  # noqa: E731
    mat = eqx.tree_at(lambda x: (x.mu, x.J, x.tau), m,
                      (pad(m.mu, 1e-9), pad(m.J, 155.0), pad(m.tau, 1.0)))
    return eqx.tree_at(lambda x: x.material, model, mat)


@pytest.fixture(scope="module")
def runs():
    sig = voltage_pattern("vp1", PEAK, PERIOD)
    out = {}
    for name in ("final", "model1", "model2"):
        model = _padded(jaxdea.load_config(CONFIGS / f"gu2017_{name}.toml"))
        _, obs, ok = solve(model, sig, TS)
        assert bool(ok)
        out[name] = {k: np.asarray(v) for k, v in obs.items()}
    return out


def test_final_model_matches_scipy_reference(runs):
    """Two VP1 cycles against scipy Radau (rtol 1e-10) of a numpy transcription solved as a
    reduced DAE (lam1 from eq 12 = P1 by brentq): within 0.5 % (measured ~3e-5)."""
    p = dict(L1=0.02, L2=0.07, H=1e-3, lam1p=1.5, lam2p=2.0, eps=4.7 * 8.854187817e-12,
             mu0=15e3, J0=155.0, mu=[150e3, 20e3, 25e3, 12e3], J=[155.0] * 4,
             tau=[0.18, 6.0, 145.0, 550.0])
    n = 2 * PTS + 1
    t = TS[:n]
    ref = planar_reference(p, lambda s: vp1(s, PEAK, PERIOD), t, [5.0, 10.0, 15.0])
    z = runs["final"]["displacement"][:n]
    err = np.max(np.abs(z - ref)) / np.max(np.abs(ref))
    assert err < 5e-3, err
    assert err < 1e-4  # far inside the requirement (dense output between steps: ~3e-5)
    assert np.allclose(runs["final"]["voltage"][:n], [vp1(s, PEAK, PERIOD) for s in t])


def _cycle_metrics(r):
    z, v = r["displacement"], r["voltage"]
    zero_v = z[::PTS]  # displacement at each zero-voltage instant t = k T
    drift_early = (zero_v[3] - zero_v[0]) / 3
    drift_late = (zero_v[12] - zero_v[9]) / 3
    areas, lags = [], []
    for c in range(CYCLES):
        sl = slice(c * PTS, (c + 1) * PTS + 1)
        areas.append(float(hysteresis_area(v[sl], z[sl])))
        lags.append(TS[sl][np.argmax(z[sl])] - TS[sl][np.argmax(v[sl])])
    return drift_early, drift_late, np.array(areas), np.array(lags), z.max()


def test_paper004_observations_final_model(runs):
    """Fig 4/9 observations, 12 cycles of VP1 (4.5 kV, 10 s): creep dominant in cycles 1-3,
    repeatable hysteresis, displacement peak after the voltage peak."""
    early, late, areas, lags, peak = _cycle_metrics(runs["final"])
    ratio = early / late
    print(f"drift ratio {ratio:.3f}, peak {peak * 1e3:.4f} mm, lag {lags[-1]:.3f} s, "
          f"areas {areas[-3:]}")
    assert early > 0 and late > 0
    assert ratio >= 3.0  # independent implementation: ~4.3
    assert 4.0 < ratio < 4.7
    assert 1.0e-3 < peak < 1.2e-3  # ~1.1 mm
    assert np.all(areas > 0)
    last = areas[-3:]
    assert (last.max() - last.min()) / last.mean() < 0.05
    assert areas[0] > last.mean()  # the first loop is the largest (creep inside it)
    assert np.all(lags > 0)  # peak displacement lags the voltage peak
    assert 0.1 <= lags[-1] <= 0.35  # ~0.2 s (sampled every 0.05 s)


def test_model2_creeps_more_than_model1(runs):
    """Section V.B: Model I (one unit) cannot reproduce the creep of cycles 1-3; Model II can."""
    creep = {k: runs[k]["displacement"][3 * PTS] - runs[k]["displacement"][0]
             for k in ("model1", "model2")}
    assert creep["model2"] > 1.5 * creep["model1"] > 0
    # Model I is nearly repeatable after the first cycle (T1 = 0.85 s << 10 s)
    z1 = runs["model1"]["displacement"][::PTS]
    assert abs(z1[3] - z1[2]) < 0.02 * abs(z1[1] - z1[0])


def test_gradients_match_finite_differences():
    """d displacement / d every material parameter (reverse mode through diffeqsolve, fixed
    implicit steps so the discrete map is smooth in the parameters) vs central differences,
    1e-4 relative (measured 1e-8 .. 4e-6). The window crosses the VP1 peak kink."""
    model = jaxdea.load_config(CONFIGS / "gu2017_final.toml")
    # the units' elastic stretches stay within a few % of 1, so with J = 155 their J barely
    # moves z (relative 1e-8: below finite-difference round-off); J_i = 0.5 makes it count
    model = eqx.tree_at(lambda m: m.material.J, model, jnp.full(4, 0.5))
    sig = voltage_pattern("vp1", PEAK, 4.0)
    ts = np.array([0.0, 1.5, 3.0, 4.0])
    w = jnp.array([0.0, 1.0, 2.0, -1.0])

    def loss(mat):
        m = eqx.tree_at(lambda x: x.material, model, mat)
        return jnp.sum(w * displacement(m, sig, ts, fixed_steps=200, rtol=1e-10, atol=1e-12))

    mat = model.material
    grad = eqx.filter_jit(jax.grad(loss))(mat)
    f = eqx.filter_jit(loss)
    scale = abs(float(f(mat)))
    names = [("mu0", None), ("J0", None)] + [(k, i) for k in ("mu", "J", "tau")
                                              for i in range(4)]
    for name, i in names:
        x = getattr(mat, name)
        xi = x if i is None else x[i]
        h = 1e-3 * float(xi)

        def shifted(d):
            new = x + d if i is None else x.at[i].add(d)
            return eqx.tree_at(lambda m: getattr(m, name), mat, new)

        fd = (f(shifted(h)) - f(shifted(-h))) / (2 * h)
        g = getattr(grad, name) if i is None else getattr(grad, name)[i]
        assert abs(float(g) - float(fd)) <= 1e-4 * abs(float(fd)), (name, i, g, fd)
        assert abs(float(fd)) * float(xi) > 1e-7 * scale  # every parameter matters


BASE = {
    "model": "planar_gu2017",
    "geometry": {"L1": 0.02, "L2": 0.07, "H": 1e-3, "lam1p": 1.5, "lam2p": 2.0,
                 "relative_permittivity": 4.7},
    "material": {"mu0": 15e3, "J0": 155.0, "mu": [150e3], "J": [155.0], "tau": [0.18]},
}


def _cfg(**material):
    return {**BASE, "material": {**BASE["material"], **material}}


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ConfigError, match=r"material\.tau\[0\].*allowed range"):
        model_from_dict(_cfg(tau=[0.0]))
    with pytest.raises(ConfigError, match=r"material\.tau\[1\]"):
        model_from_dict(_cfg(mu=[1e3, 1e3], J=[155.0, 155.0], tau=[1.0, -2.0]))
    # I1 - 3 = 3.36 at (1.5, 2): J0 = 3 locks the Gent spring up
    with pytest.raises(ConfigError, match=r"material\.J0 = 3 is below the stretch invariant"):
        model_from_dict(_cfg(J0=3.0))
    with pytest.raises(ConfigError, match=r"material\.J has 2 value\(s\)"):
        model_from_dict(_cfg(J=[155.0, 155.0]))
    with pytest.raises(ConfigError, match=r"missing key material\.tau"):
        model_from_dict({**BASE, "material": {k: v for k, v in BASE["material"].items()
                                              if k != "tau"}})
    with pytest.raises(ConfigError, match=r"geometry\.lam1p"):
        model_from_dict({**BASE, "geometry": {**BASE["geometry"], "lam1p": 0.5}})
    assert isinstance(model_from_dict(BASE), PlanarDEA)


def test_simulate_cli_writes_dataset_and_plot(tmp_path, capsys):
    """`jaxdea simulate` on the final Gu 2017 config: one VP1 cycle, NetCDF with t, voltage,
    displacement and stretches (SI units), the plot, and a bad signal rejected."""
    import xarray as xr

    from jaxdea.cli import main

    config = str(Path(__file__).parents[1] / "configs" / "gu2017_final.toml")
    out, png = tmp_path / "vp1.nc", tmp_path / "vp1.png"
    rc = main(["simulate", config, "--signal", "vp1", "--peak", "4.5e3", "--period", "10",
               "--cycles", "1", "--points", "50", "--out", str(out), "--plot", str(png)])
    assert rc == 0, capsys.readouterr().err
    ds = xr.open_dataset(out)
    assert ds.t.attrs["units"] == "s" and ds.displacement.attrs["units"] == "m"
    assert ds.voltage.attrs["units"] == "V"
    assert float(ds.voltage.max()) == pytest.approx(4.5e3, rel=1e-6)
    # the membrane thins under voltage: it moves, by about a millimetre (paper 004 scale)
    assert 2e-4 < float(abs(ds.displacement).max()) < 5e-3
    assert png.stat().st_size > 0
    with pytest.raises(SystemExit):
        main(["simulate", config, "--signal", "square", "--out", str(tmp_path / "x.nc")])
