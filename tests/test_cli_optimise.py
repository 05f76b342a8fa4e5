"""The `jaxdea optimise` command: one tiny real run (config, printout and plot agree; the
optimum is no worse than its start), and user errors that fail with one line before compute."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

import jaxdea
from jaxdea.cli import main
from jaxdea.plotting import plot_optimise
from test_cli_errors import _fails  # one definition of "exits 2 with one line"

CONFIG = str(Path(__file__).parents[1] / "configs" / "scdea_ls.toml")
BASE = ["optimise", CONFIG, "--vary", "actuator.spring_stiffness=300:600", "--mass", "2e-3",
        "--damping", "0.1"]


def test_optimise_writes_a_config_no_worse_than_its_start(tmp_path, capsys):
    out, png = tmp_path / "design.toml", tmp_path / "design.png"
    t0 = time.perf_counter()
    rc = main([*BASE, "--objective", "power", "--freq", "80", "--starts", "2", "--maxiter", "2",
               "--out", str(out), "--plot", str(png)])
    captured = capsys.readouterr()
    text = captured.out
    with capsys.disabled():  # shown with -s
        print(f"\noptimise CLI run: {time.perf_counter() - t0:.1f} s\n{text}")
    assert rc == 0, text
    # a progress bar on stderr over the evaluations (screening, 2 iterations at most, the
    # final solve from rest), with the best objective so far (W)
    bar = captured.err.replace("\r", "\n")
    assert re.search(r"optimise: +100%.* [34]/[34] .*best objective \d", bar), bar[-500:]
    k = jaxdea.load_config(out).actuator.spring_stiffness
    printed = float(re.search(r"actuator\.spring_stiffness = (\S+)", text).group(1))
    assert 300.0 <= k <= 600.0
    assert k == pytest.approx(printed, rel=1e-9)
    best = float(re.search(r"P_out at 80 Hz = (\S+) mW", text).group(1))
    start = float(re.search(r"start: (\S+) mW", text).group(1))
    assert best > 0 and best >= start  # an ascent never returns worse than its start
    assert re.search(r"gain [+-]\d+\.\d+ %", text) and "MV/m" in text and "active: " in text
    # two iterations: the run says whether it converged, never silently
    assert re.search(r"converged: (yes \(|no: stopped at --maxiter 2 )", text), text
    assert png.stat().st_size > 0 and png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args, pattern", [
    (["--vary", "prestretch=1.05"], r"--vary must be NAME=LO:HI"),
    (["--vary", "prestretch=a:2"], r"--vary .*LO and HI must be numbers"),
    (["--vary", "prestretch=1.6:1.05"], r"--vary .*LO = 1\.6 must be < HI"),
    (["--band", "40:200", "--vary", "nope=1:2"], r"--vary: unknown parameter 'nope'"),
    (["--band", "40:200", "--vary", "tau=1e-3:2e-3"], r"--vary: parameter name 'tau' is ambiguous"),
    (["--objective", "pmax"], r"--objective pmax needs --band"),
    (["--objective", "power"], r"--objective power needs --freq"),
    (["--band", "40:200", "--objective", "pmax", "--plot", "x.pdf"], r"--plot must end in \.png"),
    (["--band", "200:40"], r"--band = \(200, 40\) Hz: need 0 < f_lo < f_hi"),
    (["--band", "40:200", "--starts", "0"], r"--starts = 0 is outside the allowed range"),
])
def test_bad_arguments_fail_before_compute(tmp_path, capsys, args, pattern):
    _fails(capsys, [*BASE, *args, "--out", str(tmp_path / "d.toml")], pattern)
    assert not (tmp_path / "d.toml").exists()


def test_bad_paths_fail_before_compute(tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("keep me")
    run = [*BASE, "--band", "40:200"]
    _fails(capsys, [*run, "--out", str(blocker / "missing" / "d.toml")],
           r"--out .*is a file, not a folder")
    (tmp_path / "dir.toml").mkdir()
    _fails(capsys, [*run, "--out", str(tmp_path / "dir.toml")], r"--out .* is a directory")
    _fails(capsys, [*run, "--out", str(tmp_path / "d.nc")], r"--out must end in \.toml")
    _fails(capsys, ["optimise", str(tmp_path / "none.toml"), *run[2:], "--out",
                    str(tmp_path / "d.toml")], r"config file not found")
    assert blocker.read_text() == "keep me"


def test_help_shows_the_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["optimise", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 8)" in text and "(default: pmax)" in text and "NAME=LO:HI" in text


def test_plot_highlights_the_returned_start(tmp_path):
    """The returned start is the one whose last objective is nearest the result's (optimise
    may recompute it from rest); an infeasible start (-inf) leaves a gap, not an error."""
    history = [np.array([5e-3, 20e-3, -np.inf]), np.array([7e-3, 22.5e-3, -np.inf])]
    result = jaxdea.OptimiseResult(model=None, values={}, objective=22.5e-3 * (1 + 1e-12),
                                   f_at_P_max=None, gradient={}, active=[], field=7.9e7,
                                   start_objective=5e-3, history=history)
    fig = plot_optimise(result, objective="power")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["other starts", "start 1 (returned)"]
    plot_optimise(result, tmp_path / "h.png", objective="efficiency")
    assert (tmp_path / "h.png").read_bytes()[:4] == b"\x89PNG"
