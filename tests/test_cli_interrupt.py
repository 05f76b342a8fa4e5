"""Ctrl-C in a map keeps its finished parts and prints the --resume command; a map whose cells
all failed writes no empty plot and exits 1 (issue 13, items 5 and 6)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import xarray as xr

from jaxdea.cli import main, maps

LS = str(Path(__file__).resolve().parents[1] / "configs" / "dcdea_ls.toml")


def test_ctrl_c_prints_the_resume_command(tmp_path, capsys, monkeypatch):
    out = tmp_path / "map.zarr"
    argv = ["powermap", LS, "--mass", "1e-3:2e-3:2", "--damping", "0.1:1:2", "--freq",
            "40:60:10", "--out", str(out), "--no-progress"]

    def interrupted(*args, **kwargs):  # the user presses Ctrl-C during the compute
        raise KeyboardInterrupt

    monkeypatch.setattr(maps, "_run_powermap", interrupted)
    monkeypatch.setattr(sys, "argv", ["jaxdea", *argv])
    assert main(argv) == 130
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"Finished chunks are kept in {out}.parts" in err
    resume = err.strip().splitlines()[-1].split()
    assert resume[-1] == "--resume" and resume[1:-1] == argv  # the same command, resumed


def _failed_map(status: int) -> xr.Dataset:
    m, c = np.array([1e-3, 2e-3]), np.array([0.1, 1.0])
    nan = np.full((2, 2), np.nan)
    return xr.Dataset(
        {"P_max": (("M", "c"), nan), "f_at_P_max": (("M", "c"), nan),
         "status": (("M", "c", "f"), np.full((2, 2, 3), status)),
         "steady": (("M", "c", "f"), np.zeros((2, 2, 3), bool))},
        coords={"M": m, "c": c, "f": [40.0, 50.0, 60.0]})


def test_a_map_whose_cells_all_failed_writes_no_plot(tmp_path, capsys):
    plot = tmp_path / "map.png"
    assert maps._summarise_map(_failed_map(2), tmp_path / "map.zarr", str(plot)) == 1
    out, err = capsys.readouterr()
    assert "no steady cell finished with status 0; 12 failed cell(s)" in out
    assert f"no plot written to {plot}" in err
    assert not plot.exists()
    # without --plot, the summary alone is not an error
    assert maps._summarise_map(_failed_map(2), tmp_path / "map.zarr", None) == 0
