"""A user's mistake gives one clear line and a non-zero exit code, before any compute: never a
traceback, never a lost result (issue 13, items 4-6). Each case is one a new user hit."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import jaxdea
from jaxdea.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
LS = str(CONFIGS / "dcdea_ls.toml")
ROTARY = str(CONFIGS / "rotary_dcdea.toml")
SWEEP = ["sweep", LS, "--mass", "2e-3", "--damping", "0.1", "--freq", "40:60:10",
         "--cycles", "4", "--average", "2"]


def _fails(capsys, argv, pattern):
    """``main(argv)`` exits 2 with a single line on stderr matching ``pattern``."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("jaxdea: error: ")
    assert re.search(pattern, err), err
    return err


def test_plot_must_be_png_for_every_command(tmp_path, capsys):
    _fails(capsys, [*SWEEP, "--out", str(tmp_path / "s.nc"), "--plot", str(tmp_path / "s.pdf")],
           r"--plot must end in \.png")
    assert not (tmp_path / "s.nc").exists()  # refused before the compute


def test_output_under_a_file_or_onto_a_folder_is_refused_before_compute(tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("keep me")
    _fails(capsys, [*SWEEP, "--out", str(blocker / "sub" / "s.nc")], r"--out .* is a file")
    (tmp_path / "dir.nc").mkdir()
    _fails(capsys, [*SWEEP, "--out", str(tmp_path / "dir.nc")], r"--out .* is a directory")
    _fails(capsys, [*SWEEP, "--out", str(tmp_path / "s.nc"), "--plot",
                    str(blocker / "p.png")], r"--plot .* is a file")
    assert blocker.read_text() == "keep me"


def test_config_path_that_is_a_directory(tmp_path, capsys):
    _fails(capsys, ["sweep", str(tmp_path), "--mass", "2e-3", "--damping", "0.1", "--freq",
                    "40:60:10", "--out", str(tmp_path / "s.nc")], r"is a directory")


def test_config_of_another_family_is_named(tmp_path, capsys):
    _fails(capsys, ["sweep", ROTARY, "--mass", "2e-3", "--damping", "0.1", "--freq",
                    "40:60:10", "--out", str(tmp_path / "s.nc")],
           r"square-wave cone .*got RotaryDCDEA")
    _fails(capsys, ["powermap", ROTARY, "--mass", "1e-3:2e-3:2", "--damping", "0.1:1:2",
                    "--freq", "40:60:10", "--out", str(tmp_path / "m.zarr")],
           r"square-wave cone .*got RotaryDCDEA")


@pytest.mark.parametrize("rtol", ["-1", "2", "0", "nan"])
def test_sweep_rejects_a_bad_tolerance(tmp_path, capsys, rtol):
    _fails(capsys, [*SWEEP, "--rtol", rtol, "--out", str(tmp_path / "s.nc")],
           r"rtol = .* allowed range \(0, 1\)")


def test_phase_without_drive_both_is_refused(tmp_path, capsys):
    _fails(capsys, [*SWEEP, "--phase", "1", "--out", str(tmp_path / "s.nc")],
           r"phase = 1\.0 rad is only used with drive='both'")


def test_python_api_names_the_mistake():
    model = jaxdea.load_config(LS)
    with pytest.raises(jaxdea.ConfigError, match="use jaxdea.load_config"):
        jaxdea.sweep(LS, mass=2e-3, damping=0.1, freq=[50.0])
    with pytest.raises(jaxdea.SweepError, match="control must be a jaxdea.StepControl"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[50.0], control=(1e-6,))
    with pytest.raises(jaxdea.SweepError, match=r"rtol = -1"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[50.0],
                     control=jaxdea.StepControl(rtol=-1.0))
    with pytest.raises(jaxdea.SweepError, match="phase"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[50.0], drive="A", phase=1.0)


def test_version_and_defaults_in_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxdea {jaxdea.__version__}"
    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 100)" in text and "membrane A only" in text


def test_plot_of_a_sweep_file_or_a_truncated_map(tmp_path, capsys):
    sweep_nc = tmp_path / "s.nc"
    assert main([*SWEEP, "--out", str(sweep_nc)]) == 0
    capsys.readouterr()
    _fails(capsys, ["plot", str(sweep_nc), "--kind", "pmax", "--out", str(tmp_path / "p.png")],
           r"s\.nc is a frequency sweep")
    cut = tmp_path / "cut.nc"
    cut.write_bytes(sweep_nc.read_bytes()[:200])
    _fails(capsys, ["plot", str(cut), "--kind", "pmax", "--out", str(tmp_path / "p.png")],
           r"cut\.nc is not a readable power map")
    assert not (tmp_path / "p.png").exists()


def test_a_file_jaxdea_did_not_write_is_never_replaced(tmp_path, capsys):
    """``--out`` and ``--plot`` onto a user's file (data, a hand-written config, a figure made
    elsewhere) are refused before any compute, and the file is untouched; the same command
    may replace its own output (jaxdea's mark: :mod:`jaxdea.provenance`)."""
    data, figure = tmp_path / "measured.nc", tmp_path / "figure.png"
    data.write_bytes(b"precious")
    figure.write_bytes(b"\x89PNG\r\n\x1a\nnot jaxdea's")
    _fails(capsys, [*SWEEP, "--out", str(data)], r"--out .*measured\.nc exists and jaxdea did "
                                                  r"not write it")
    _fails(capsys, [*SWEEP, "--out", str(tmp_path / "s.nc"), "--plot", str(figure)],
           r"--plot .*figure\.png exists and jaxdea did not write it")
    config = tmp_path / "mine.toml"
    config.write_text(Path(LS).read_text())
    # calibrating a config in place would overwrite it: refused before the fit
    _fails(capsys, ["calibrate", str(config), "--data", str(data), "--fit", "dielectric.mu_A",
                    "--out", str(config)], r"--out .*mine\.toml exists and jaxdea did not")
    _fails(capsys, ["optimise", str(config), "--vary", "spring_stiffness=300:700", "--mass",
                    "2e-3", "--damping", "0.1", "--band", "40:120", "--out", str(config)],
           r"--out .*mine\.toml exists and jaxdea did not")
    assert data.read_bytes() == b"precious" and config.read_text() == Path(LS).read_text()
    assert figure.read_bytes().endswith(b"not jaxdea's")


def test_a_negative_value_after_its_option_gets_the_range_check(tmp_path, capsys):
    """``--mass -1e-3`` (no ``=``): argparse would take ``-1e-3`` for an option and answer with
    its usage; the value reaches the range check instead, and so do negative ranges."""
    out = str(tmp_path / "s.nc")
    base = ["sweep", LS, "--freq", "40:60:10", "--out", out]
    _fails(capsys, [*base, "--mass", "-1e-3", "--damping", "0.1"],
           r"mass must be >= 0 \(allowed range \[0, inf\)\)")
    _fails(capsys, [*base, "--mass", "2e-3", "--damping", "-.5"], r"damping must be >= 0")
    _fails(capsys, ["rotary-study", ROTARY, "--ri", "-2e-3:7e-3:3", "--d", "4e-3:18e-3:3",
                    "--out", out], r"ri must be > 0 \(allowed range \(0, inf\)\)")
    assert not Path(out).exists()
