"""Per-cell honesty: the ``steady`` flag, batch-independent numbers for steady cells, and the
breakdown-field warning (reliability issue: a 40 kV map reported 0 failed cells while most
cells were not periodic, and changed with ``--chunk``)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import jaxdea
from jaxdea import FieldWarning
from jaxdea.cli import main
from jaxdea.cli.maps import _summarise_map
from jaxdea.engine.metrics import STEADY_RESIDUAL, steady_cells
from jaxdea.studies import powermap as pm
from jaxdea.studies import simulate as sim
from jaxdea.studies import sweep as sw

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
LS = CONFIGS / "dcdea_ls.toml"
NUMBERS = ("P_out", "P_in", "P_in_signed", "efficiency", "amplitude", "v_rms", "residual",
           "steps", "cycles_run")


def _config(tmp_path, voltage="4e4", extra=""):
    """dcdea_ls.toml with another drive voltage (and extra [drive] lines)."""
    text = LS.read_text().replace("voltage = 4.9e3", f"voltage = {voltage}\n{extra}")
    path = tmp_path / "ls.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def ls40(tmp_path_factory):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FieldWarning)
        return jaxdea.load_config(_config(tmp_path_factory.mktemp("v40")))


def test_steady_rule():
    status = np.array([0, 0, 0, 4, 1, 2, 3, 0])
    res = np.array([0.0, STEADY_RESIDUAL, 1.01 * STEADY_RESIDUAL, 1e-5, 1e-9, 1e-9, 1e-9,
                    np.nan])
    np.testing.assert_array_equal(steady_cells(status, res),
                                  [True, True, False, True, False, False, False, False])


def test_p_max_only_over_steady_cells():
    ds = xr.Dataset({"P_out": (("c", "f"), [[1.0, 9.0], [5.0, 6.0]]),
                     "status": (("c", "f"), [[0, 0], [0, 0]]),
                     "steady": (("c", "f"), [[True, False], [False, False]])},
                    coords={"c": [1.0, 2.0], "f": [10.0, 20.0]})
    out = pm.reduce_over_f(ds)
    np.testing.assert_array_equal(out.P_max.values, [1.0, np.nan])
    np.testing.assert_array_equal(out.f_at_P_max.values, [10.0, np.nan])
    assert "steady" in out.P_max.attrs["long_name"]


def _agree(a, b, label):
    """Steady cells: same status and numbers to 1e-9 relative; cells that differ must be
    flagged not steady in both runs. Returns the number of steady cells."""
    sa, sb = a["steady"].values.ravel(), b["steady"].values.ravel()
    differ = a["status"].values.ravel() != b["status"].values.ravel()
    for k in NUMBERS:
        x, y = a[k].values.ravel().astype(float), b[k].values.ravel().astype(float)
        differ |= ~np.isclose(x, y, rtol=1e-9, atol=0.0, equal_nan=True)
    np.testing.assert_array_equal(sa & differ, False, err_msg=label)
    np.testing.assert_array_equal(sb & differ, False, err_msg=label)
    np.testing.assert_array_equal(sa, sb, err_msg=label)
    return int(sa.sum())


@pytest.mark.filterwarnings("ignore::jaxdea.FieldWarning")
def test_steady_cells_do_not_depend_on_the_batch(ls40):
    """The same 40 kV cells in different batch compositions: one batch, one cell per batch
    (a one-lane pool: it used to round differently), two per batch, and sweeps over other
    frequency sets. Steady cells agree to 1e-9 with identical status."""
    freq = np.array([20.0, 40.0, 60.0, 80.0, 100.0])
    kw = dict(mass=[1e-4], damping=[1.0], freq=freq, cycles=12, average=2, progress=False)
    ref = pm.powermap(ls40, **kw)
    for chunk in (1, 2):
        got = pm.powermap(ls40, chunk_cells=chunk, **kw)
        _agree(ref, got, f"chunk_cells={chunk}")
        if chunk == 1:  # a cell alone runs in a 2-lane pool (MIN_LANES): on the CPU the
            # same bits as in company, chaotic cells included
            xr.testing.assert_identical(ref.drop_attrs(), got.drop_attrs())
    ref_f = ref.isel(M=0, c=0)
    swp = dict(mass=1e-4, damping=1.0, cycles=12, average=2)
    full = sw.sweep(ls40, freq=freq, **swp)
    n_steady = _agree(ref_f, full, "sweep vs map")
    for sub in ([60.0], [40.0, 80.0]):
        part = sw.sweep(ls40, freq=sub, **swp)
        _agree(full.sel(f=sub), part, f"sweep over {sub}")
    assert 2 <= n_steady < freq.size  # both kinds of cell are in the test
    # the cells flagged not steady are the ones whose numbers mean nothing: a change of
    # the step tolerance (a perturbation of the order of the integration error) moves
    # their P_out by O(1); the steady cells move by about the integration error
    other = sw.sweep(ls40, freq=freq, control=jaxdea.StepControl(rtol=2e-6), **swp)
    change = np.abs(other.P_out.values / full.P_out.values - 1)
    steady = full.steady.values
    assert np.all(change[steady] < 1e-4), change
    assert np.any(change[~steady] > 1e-2), change


def test_default_drive_is_below_breakdown(models):
    ls = models["dcdea_ls"]
    assert float(ls.nominal_field()) == pytest.approx(79.97e6, rel=1e-3)  # paper 000's 80 MV/m
    assert ls.breakdown_field == jaxdea.membrane.BREAKDOWN_FIELD
    for model in models.values():
        assert float(model.nominal_field()) < model.breakdown_field


def test_studies_warn_before_compute(ls40, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("computed")

    monkeypatch.setattr(sw, "run_cells", boom)
    monkeypatch.setattr(pm, "_run_chunk", boom)
    monkeypatch.setattr(sim, "_solve", boom)
    calls = (lambda: sw.sweep(ls40, mass=1e-3, damping=0.1, freq=[40.0]),
             lambda: pm.powermap(ls40, mass=[1e-3], damping=[0.1], freq=[40.0],
                                 progress=False),
             lambda: sim.simulate(ls40, mass=1e-3, damping=0.1, freq=40.0))
    for call in calls:
        with pytest.warns(FieldWarning, match=r"nominal field 652\.8 MV/m .* 6\.53x the "
                                              r"breakdown field 100 MV/m"):
            with pytest.raises(RuntimeError, match="computed"):
                call()


def test_breakdown_field_is_configurable(tmp_path, monkeypatch):
    model = jaxdea.load_config(_config(tmp_path, extra="breakdown_field = 1e9"))
    assert model.breakdown_field == 1e9
    monkeypatch.setattr(sw, "run_cells", lambda *a, **k: (_ for _ in ()).throw(
        RuntimeError("computed")))
    with warnings.catch_warnings():
        warnings.simplefilter("error", FieldWarning)  # 652.8 MV/m < 1000 MV/m: no warning
        with pytest.raises(RuntimeError):
            sw.sweep(model, mass=1e-3, damping=0.1, freq=[40.0])
    with pytest.raises(jaxdea.ConfigError, match=r"drive\.breakdown_field = -1"):
        jaxdea.load_config(_config(tmp_path, extra="breakdown_field = -1"))


def test_cli_prints_the_warning_as_one_line(tmp_path, capsys, monkeypatch):
    def refuse(*a, **k):
        raise jaxdea.SweepError("stop here")

    monkeypatch.setattr(sw, "run_cells", refuse)
    argv = ["sweep", str(_config(tmp_path)), "--mass", "1e-3", "--damping", "0.1",
            "--freq", "40:40:10", "--out", str(tmp_path / "x.nc")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2, err
    assert err[0].startswith("jaxdea: warning: nominal field 652.8 MV/m")
    assert err[1] == "jaxdea: error: stop here"


def test_cli_summary_counts_not_steady_cells(tmp_path, capsys):
    ds = xr.Dataset({"P_out": (("M", "c", "f"), [[[1.0, 9.0, 2.0, 3.0, 4.0]]]),
                     "status": (("M", "c", "f"), [[[0, 0, 2, 4, 4]]]),
                     "steady": (("M", "c", "f"), [[[True, False, False, True, True]]])},
                    coords={"M": [1e-3], "c": [0.1], "f": [10.0, 20.0, 30.0, 40.0, 50.0]})
    assert _summarise_map(pm.reduce_over_f(ds), tmp_path / "x.nc", None) == 0
    out = capsys.readouterr().out
    assert "P_max (steady cells) 1000.000 mW" in out and "f = 10 Hz; 3 failed cell(s)" in out
    # the failed cells counted by status code, with what each code means
    assert f"\n  1 cell(s) with status 2: {jaxdea.STATUS[2]}\n" in out
    assert f"\n  2 cell(s) with status 4: {jaxdea.STATUS[4]}\n" in out
    assert (f"1 cell(s) not steady (periodicity residual above {STEADY_RESIDUAL:g}): their "
            "averages are not a steady-state power") in out
    assert "second stable orbit" not in out  # a map from rest has no coexist variable
    ds["coexist"] = ds["steady"] & (ds["status"] == 4)  # two cells flagged
    assert _summarise_map(pm.reduce_over_f(ds), tmp_path / "x.nc", None) == 0
    assert ("2 cell(s) with a second stable orbit (variable 'coexist'): the map reports the "
            "branch continued from the heavier loads") in capsys.readouterr().out


def test_newton_solve_survives_singular_and_non_finite_cells():
    from jaxdea.engine.periodic import floquet_radius, newton_step

    jac = np.stack([np.diag([0.5, 0.2]), np.eye(2), np.full((2, 2), np.nan),
                    np.diag([0.5, 0.2])])  # ok, J - I singular, not finite, inactive
    gap = np.ones((4, 2))
    step = newton_step(jac, gap, np.array([True, True, True, False]))
    assert np.allclose(step[0], [2.0, 1.25])  # -(J - I)^-1 gap
    assert np.isnan(step[1:3]).all()  # no Newton step, and no exception for the batch
    assert (step[3] == 0).all()
    rho = floquet_radius(np.stack([np.diag([0.5, -1.5]), np.array([[0.0, 2.0], [-0.5, 0.0]])]))
    assert np.allclose(rho, [1.5, 1.0])


def test_radius_above_decides_as_the_eigenvalues_do():
    """The power-norm screen of ``radius_above`` (a Jacobian in SI units, far from normal)
    never changes a stability decision: the same as comparing numpy's eigenvalues."""
    from jaxdea.engine.periodic import floquet_radius, radius_above

    rng = np.random.default_rng(3)
    scale = np.diag([1e-7, 1e-3, 1.0, 10.0, 1e4])  # charge, displacement, ... magnitudes
    jac = scale @ (rng.normal(size=(4000, 5, 5)) * rng.uniform(0.05, 0.45, (4000, 1, 1))) \
        @ np.linalg.inv(scale)
    jac[0], jac[1], jac[2] = np.nan, 0.0, np.diag([0.98, 0.1, 0.1, 0.1, 0.1])
    jac[3] = np.diag([0.9799, 0.1, 0.1, 0.1, 0.1])
    rho = floquet_radius(jac)
    for bound in (0.5, 0.98, 1.001):
        above = radius_above(jac, bound)
        assert (above == ~(rho <= bound)).all()
        assert 0.02 < above.mean() < 0.98  # both outcomes exercised
    assert radius_above(jac, 0.98)[0] and not radius_above(jac, 0.98)[1:4].any()


def test_periodic_protocol_reports_what_the_actuator_reaches(ls40):
    """At 40 kV, Newton shooting from a trajectory that never settles used to end in a
    reported Gent lock-up (the extrapolated iterate locked up, not the actuator) or on an
    unstable orbit with another P_out. Both are status 4 now; cells the 100-cycle run
    finds steady agree with it."""
    kw = dict(mass=np.array([1e-4]), damping=np.array([0.01, 0.1, 1.0]),
              freq=np.array([20.0, 80.0]), progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FieldWarning)
        paper = jaxdea.powermap(ls40, **kw)
        periodic = jaxdea.powermap(ls40, protocol="periodic", **kw)
    assert (paper.status == 0).all()
    wild = paper.residual.values > 0.1  # the 100-cycle run is far from periodic there
    assert wild.sum() >= 2  # the case is exercised
    st = periodic.status.values
    assert set(np.unique(st)) <= {0, 4}  # never a lock-up that only a Newton iterate had
    assert (st[wild] == 4).all() and not periodic.steady.values[wild].any()
    both = (st == 0) & (paper.residual.values < 0.05)
    assert both.sum() >= 2
    assert np.allclose(periodic.P_out.values[both], paper.P_out.values[both], rtol=1e-3)
