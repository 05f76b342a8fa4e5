"""The `jaxdea sweep` command: writes NetCDF + plot; bad arguments fail before computing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from jaxdea.cli import main
from jaxdea.cli.args import parse_range

CONFIG = str(Path(__file__).parents[1] / "configs" / "scdea_ls.toml")


def test_sweep_writes_dataset_and_plot(tmp_path, capsys):
    out, png = tmp_path / "s.nc", tmp_path / "s.png"
    rc = main(["sweep", CONFIG, "--mass", "2e-3", "--damping", "0.1", "--freq", "80:90:5",
               "--cycles", "20", "--average", "5", "--out", str(out), "--plot", str(png)])
    assert rc == 0
    ds = xr.open_dataset(out, engine="h5netcdf")
    np.testing.assert_allclose(ds.f.values, [80.0, 85.0, 90.0])
    assert ds.P_out.attrs["units"] == "W" and ds.amplitude.attrs["units"] == "m"
    assert ds.f.attrs["units"] == "Hz"
    assert np.all(ds.status.values == 0)
    assert np.all(ds.P_in.values >= ds.P_out.values) and np.all(ds.P_out.values > 0)
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "P_out max" in capsys.readouterr().out
    assert not (tmp_path / "s.nc.part").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--freq", "40:20:1"], "--freq is empty"),
        (["--freq", "0:20:1"], "freq must be > 0"),
        (["--freq", "10:20:0"], "STEP must be > 0"),
        (["--freq", "10:nan:1"], "must be finite"),
        (["--freq", "10:20"], "MIN:MAX:STEP"),
        (["--mass", "-1"], "mass must be >= 0"),
        (["--damping", "inf"], "damping must be finite"),
        (["--drive", "B"], "has one membrane"),
        (["--cycles", "5", "--average", "6"], "average = 6 must be <= cycles = 5"),
    ],
)
def test_bad_arguments_fail_before_compute(tmp_path, capsys, args, message):
    base = {"--mass": "2e-3", "--damping": "0.1", "--freq": "80:90:5"}
    argv = ["sweep", CONFIG, "--out", str(tmp_path / "x.nc")]
    for k, v in base.items():
        if k not in args:
            argv += [k, v]
    rc = main(argv + args)
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.nc").exists()


def test_parse_range_is_inclusive():
    np.testing.assert_allclose(parse_range("1:200:0.2")[[0, -1]], [1.0, 200.0])
    assert parse_range("1:200:0.2").size == 996
