"""Bad values given in code are refused before any compute, with one line naming the value
and its allowed range (the config's own), and jaxdea's outputs carry the mark that lets a
rerun replace them (:mod:`jaxdea.provenance`). Each case is one an input audit found."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
import xarray as xr

import jaxdea
from jaxdea.provenance import MARK, written_by_jaxdea

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIGS / "scdea_ls.toml")


KW = dict(mass=2e-3, damping=0.1, band=(40.0, 200.0))


@pytest.mark.parametrize("call,match", [
    (lambda m: jaxdea.peak_power(m, {"actuator.spring_stiffness": -500.0}, **KW),
     r"actuator\.spring_stiffness = -500\.0 is outside the allowed range \[0, inf\) N/m"),
    (lambda m: jaxdea.steady_objectives(m, {"membrane.prestretch": 0.9}, mass=2e-3,
                                        damping=0.1, freq=60.0),
     r"membrane\.prestretch = 0\.9 is outside the allowed range \[1, 10\]"),
    (lambda m: jaxdea.design_map(m, {"mass": [-1e-3, 1e-3]}, damping=0.1, band=(40.0, 200.0),
                                 progress=False),
     r"mass = -0\.001 is outside the allowed range \[0, inf\) kg"),
    (lambda m: jaxdea.design_map(m, {"duty": [0.5, 1.0]}, **KW, progress=False),
     r"duty = 1\.0 is outside the allowed range \(0, 1\)"),
    (lambda m: jaxdea.optimise(m, {"actuator.spring_stiffness": (-500.0, -100.0)}, **KW),
     r"vary\['actuator\.spring_stiffness'\] = -500\.0 is outside the allowed range"),
    (lambda m: jaxdea.optimise(m, {"membrane.thickness": (0.0, 1e-4)}, **KW),
     r"vary\['membrane\.thickness'\] = 0\.0 is outside the allowed range \(0, inf\) m"),
    (lambda m: jaxdea.sweep(m, mass="heavy", damping=0.1, freq=[60.0]),
     r"mass must be a number or an array of numbers, got 'heavy'"),
    (lambda m: jaxdea.sweep(m, mass=2e-3, damping=0.1, freq="100"),
     r"freq must be a number or an array of numbers, got '100'"),
    (lambda m: jaxdea.rotary_study(jaxdea.load_config(CONFIGS / "rotary_dcdea.toml"),
                                   [-2e-3, 5e-3], [4e-3]),
     r"ri must be > 0 \(allowed range \(0, inf\)\)"),
])
def test_out_of_range_values_are_refused_before_compute(model, call, match):
    with pytest.raises(jaxdea.SweepError, match=match):
        call(model)


def test_a_config_is_a_path():
    with pytest.raises(jaxdea.ConfigError, match=r"a config is a path to a \.toml file, got 42"):
        jaxdea.load_config(42)


def test_a_design_map_over_payload_axes_only(model, monkeypatch):
    """Only the payload varies (no model parameter): every design has the model's own nominal
    field. (This crashed after the whole peak search: the field was computed by setting no
    parameter at all.) The peak search is replaced by a stand-in here: what is checked is
    the map's assembly; test_design.py checks its numbers."""
    from jaxdea.studies import design
    from jaxdea.studies.loadings import nominal_field

    def stand_in(build, theta, band, **kw):
        n = theta.shape[0]
        return {"P_max": theta[:, 0], "f": np.full(n, 80.0), "status": np.zeros(n, int),
                "metrics": np.ones((n, len(design.METRICS)))}

    monkeypatch.setattr(design, "peak_designs", stand_in)
    ds = jaxdea.design_map(model, {"mass": [1e-3, 2e-3, 3e-3]}, damping=0.1,
                           band=(40.0, 200.0), progress=False)
    np.testing.assert_array_equal(ds.P_max, [1e-3, 2e-3, 3e-3])  # theta is the mass
    np.testing.assert_allclose(ds.field, float(nominal_field(model)), rtol=0)


def test_jaxdea_marks_what_it_writes(model, tmp_path):
    """Datasets, PNG figures and TOML configs written by jaxdea carry its mark; the same
    kinds of file written otherwise do not; a fitted config keeps one mark line."""
    from jaxdea.calibration import write_fitted_config
    from jaxdea.cli.args import write_dataset
    from jaxdea.plotting import _save
    from jaxdea.studies.optimise import write_cone_toml

    ds = xr.Dataset({"P_out": ("f", np.arange(3.0))})
    write_dataset(ds, tmp_path / "ours.nc")
    ds.to_netcdf(tmp_path / "theirs.nc", engine="h5netcdf")
    fig, _ = plt.subplots()
    _save(fig, tmp_path / "ours.png")
    fig, _ = plt.subplots()
    fig.savefig(tmp_path / "theirs.png")
    plt.close(fig)
    toml = write_cone_toml(model, tmp_path / "ours.toml", header="a test")
    assert jaxdea.load_config(toml).actuator.name == model.actuator.name  # still a config
    fitted = write_fitted_config(toml, tmp_path / "fitted.toml",
                                 {"actuator.spring_stiffness": 512.0})
    assert fitted.read_text().count(MARK) == 1
    assert float(jaxdea.load_config(fitted).actuator.spring_stiffness) == 512.0
    for name in ("ours.nc", "ours.png", "ours.toml", "fitted.toml"):
        assert written_by_jaxdea(tmp_path / name), name
    for name in ("theirs.nc", "theirs.png", "missing.png"):
        assert not written_by_jaxdea(tmp_path / name), name
    assert not written_by_jaxdea(CONFIGS / "scdea_ls.toml")  # hand-written
    # the API writers refuse a user's file too
    with pytest.raises(jaxdea.SweepError, match="jaxdea did not write it"):
        write_cone_toml(model, tmp_path / "theirs.png")
    with pytest.raises(jaxdea.CalibrationError, match="jaxdea did not write it"):
        write_fitted_config(toml, tmp_path / "theirs.nc", {"actuator.spring_stiffness": 1.0})


def test_resume_does_not_replace_a_finished_map(model, tmp_path):
    """``resume=True`` continues an interrupted run (its ``.parts`` beside the store); on a
    finished map there is nothing to resume, and recomputing would replace it unasked."""
    store = tmp_path / "map.nc"
    xr.Dataset({"P_out": ("f", np.arange(3.0))},
               attrs={"jaxdea_version": "0"}).to_netcdf(store, engine="h5netcdf")
    with pytest.raises(jaxdea.SweepError, match=r"nothing to resume: .*map\.nc is a finished"):
        jaxdea.powermap(model, mass=[1e-3], damping=[0.1], freq=[60.0], store=store,
                        resume=True, progress=False)
    assert written_by_jaxdea(store)


def test_a_model_edited_in_code_is_checked_as_a_config_would_be(model):
    """A model whose parameter was set out of its config range in code (``set_params``) is
    refused by the sweep and the map before any compute, naming the parameter."""
    bad = jaxdea.params.set_params(model, {"actuator.spring_stiffness": -500.0})
    match = r"actuator\.spring_stiffness = -500\.0 is outside the allowed range \[0, inf\) N/m"
    with pytest.raises(jaxdea.ConfigError, match=match):
        jaxdea.sweep(bad, mass=2e-3, damping=0.1, freq=[60.0])
    with pytest.raises(jaxdea.ConfigError, match=match):
        jaxdea.powermap(bad, mass=[2e-3], damping=[0.1], freq=[60.0], progress=False)
    thin = jaxdea.params.set_params(model, {"membrane.prestretch": 12.0})
    with pytest.raises(jaxdea.ConfigError, match=r"prestretch = 12\.0 is outside .*\[1, 10\]"):
        jaxdea.sweep(thin, mass=2e-3, damping=0.1, freq=[60.0])
