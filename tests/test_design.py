"""Design study: optimise() (a stationary feasible design, the field limit, its input
checks) and the batched design map."""

import jax
import numpy as np
import pytest

import jaxdea
from jaxdea.studies.design import resolve
from jaxdea.studies.optimise import nominal_field, optimise


def test_optimise_returns_a_stationary_feasible_design(models, tmp_path, capfd):
    model = models["scdea_ls"]
    vary = {"actuator.spring_stiffness": (100.0, 2000.0), "membrane.prestretch": (1.05, 1.3)}
    res = optimise(model, vary, "power", mass=2e-3, damping=0.1, freq=60.0, starts=2,
                   maxiter=25, gtol=1e-3, progress=False)
    assert "optimise" not in capfd.readouterr().err  # no progress bar when asked for none
    assert res.field <= 80e6  # never a design above max_field
    assert float(nominal_field(res.model)) <= 80e6
    assert res.objective >= res.start_objective
    assert res.converged and res.stopped in ("gradient", "step")  # before maxiter = 25
    assert np.isclose(res.metrics["P_out"], res.objective)  # the objective's own orbit
    assert 0 < res.metrics["efficiency"] < 1 and res.metrics["P_in"] > res.objective
    assert len(res.path) == len(res.history) and res.path[0].shape == (2, 2)
    lo = np.array([b[0] for b in vary.values()])
    hi = np.array([b[1] for b in vary.values()])
    x = (np.array(list(res.values.values())) - lo) / (hi - lo)
    g = np.array(list(res.gradient.values())) * (hi - lo)
    at = (x <= 0) | (x >= 1)
    field_active = any("field" in a for a in res.active)
    if not field_active:
        pg = np.where((x <= 0) & (g < 0) | (x >= 1) & (g > 0), 0.0, g)
        assert np.abs(pg).max() <= 1e-2 * res.objective, (res.values, res.gradient)
    assert np.all((x[~at] > 0) & (x[~at] < 1))
    back = jaxdea.load_config(res.to_toml(tmp_path / "opt.toml"))
    for k, v in res.values.items():
        assert np.isclose(float(jaxdea.parameter_names(back)[resolve(model, [k])[k]]), v)


def test_starts_above_the_field_limit_are_pulled_back_to_it():
    from jaxdea.studies.optimise import _pull_inside

    def fields(x):  # a field that grows with the first variable: limit at x0 = 0.5
        return 160e6 * np.asarray(x)[:, 0]

    x = np.array([[0.2, 0.5], [0.9, 0.1], [0.4, 0.9], [1.0, 1.0]])
    y = _pull_inside(x, fields, 80e6)
    assert (fields(y) <= 80e6).all()
    assert np.allclose(fields(y[[1, 3]]), 80e6, rtol=1e-7)  # moved to the limit, not beyond
    assert (y[[0, 2]] == x[[0, 2]]).all()  # feasible starts untouched
    t = (y[1] - x[0]) / (x[1] - x[0])
    assert np.allclose(t, t[0])  # on the line towards the first start
    assert (_pull_inside(x[::-1], fields, 80e6) == x[::-1]).all()  # first start infeasible


BAD = [
    (dict(vary={"nonsense": (1.0, 2.0)}), "nonsense"),
    (dict(vary={"actuator.spring_stiffness": (2000.0, 100.0)}), "lower must be < upper"),
    (dict(vary={"actuator.spring_stiffness": (100.0, float("inf"))}), "finite"),
    (dict(vary={"actuator.spring_stiffness": (100.0, 2000.0)}, band=(50.0, 10.0)), "f_lo"),
    (dict(vary={"actuator.spring_stiffness": (100.0, 2000.0)}, starts=0), "starts"),
    (dict(vary={"actuator.spring_stiffness": (100.0, 2000.0)}, x0={
        "actuator.spring_stiffness": 5000.0}), "outside its bounds"),
    (dict(vary={"actuator.spring_stiffness": (100.0, 2000.0)}, max_field=float("nan")),
     "max_field"),
]


@pytest.mark.parametrize("kw,match", BAD)
def test_bad_inputs_raise_sweep_error(models, kw, match):
    kw = dict(dict(objective="pmax", mass=2e-3, damping=0.1, band=(10.0, 100.0)), **kw)
    with pytest.raises(jaxdea.SweepError, match=match):
        optimise(models["scdea_ls"], **kw)


def test_design_map_equals_one_design_at_a_time(models):
    """The batched map over designs gives each design's own P_max (cells are independent),
    its efficiency at the peak, and its nominal field."""
    model = models["scdea_ls"]
    kw = dict(mass=2e-3, damping=0.1, band=(20.0, 160.0), grid=4, refine=1)
    ds = jaxdea.design_map(model, {"actuator.spring_stiffness": [300.0, 700.0],
                                   "membrane.prestretch": [1.15]}, progress=False, **kw)
    assert ds.P_max.dims == ("actuator.spring_stiffness", "membrane.prestretch")
    assert (ds.status == 0).all()
    for i, k in enumerate([300.0, 700.0]):
        values = {"actuator.spring_stiffness": k, "membrane.prestretch": 1.15}
        one = jaxdea.peak_power(model, values, **kw) if i == 0 else jaxdea.peak_power(
            jaxdea.params.set_params(model, values), **kw)  # and nothing varied
        cell = ds.isel({"actuator.spring_stiffness": i, "membrane.prestretch": 0})
        assert np.isclose(float(cell.P_max), float(one["P_max"]), rtol=1e-9)
        assert np.isclose(float(cell.f_at_P_max), float(one["f_at_P_max"]), rtol=1e-9)
        assert 0 < float(cell.efficiency) < 1
        assert np.isclose(float(cell.P_max) / float(cell.P_in), float(cell.efficiency))
        field = nominal_field(jaxdea.params.set_params(model, {
            "actuator.spring_stiffness": k, "membrane.prestretch": 1.15}))
        assert np.isclose(float(cell.field), float(field), rtol=1e-12)
    assert float(ds.P_max[0, 0]) != float(ds.P_max[1, 0])  # the designs differ
    # P_max under jax.grad (the refinement levels' warm starts stay host arrays): the
    # envelope-theorem gradient agrees with a central difference
    v = {"actuator.spring_stiffness": 300.0, "membrane.prestretch": 1.15}
    g = jax.grad(lambda v: jaxdea.peak_power(model, v, **kw)["P_max"])(v)
    h = 1e-5 * 300.0
    fd = [float(jaxdea.peak_power(model, dict(v, **{"actuator.spring_stiffness": 300.0 + s * h}),
                                  **kw)["P_max"]) for s in (1, -1)]
    assert np.isclose(g["actuator.spring_stiffness"], (fd[0] - fd[1]) / (2 * h), rtol=1e-3)
