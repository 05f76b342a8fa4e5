"""What every command shares: range and grid parsing, output-path checks, the protocol options,
atomic NetCDF writing, and the count of failed results by status code."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np

from jaxdea.engine.step_control import (
    AUTO,
    EXTRAPOLATE,
    EXTRAPOLATE_FROM,
    SOLVERS,
    StepControl,
)
from jaxdea.provenance import check_replaceable_file, jaxdea_version

#: The most points one command-line range may hold: a guard against a typo (``1:100:1e-9``)
#: that would allocate terabytes before any check; a larger grid is several runs.
MAX_POINTS = 1_000_000


def _grid(values: np.ndarray, text: str, name: str) -> np.ndarray:
    """``values`` if they are finite and strictly increasing (distinct grid points at float64
    precision); else ``ValueError`` naming the option."""
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{name} {text!r} overflows a float64: keep MIN, MAX and MAX - MIN "
                         "within (-1e308, 1e308)")
    if not np.all(np.diff(values) > 0):
        raise ValueError(f"{name} {text!r} has points that are equal at float64 precision: "
                         "widen MAX - MIN or use fewer points")
    return values


def parse_range(text: str, name: str = "--freq") -> np.ndarray:
    """``MIN:MAX:STEP`` -> inclusive arithmetic range (``MAX`` included when on the grid).

    Arguments:
        text: the option's value, ``MIN:MAX:STEP`` (finite numbers, ``STEP > 0``, at most
            :data:`MAX_POINTS` points).
        name: the option, named in the error message.

    Returns:
        The finite, strictly increasing points (``ValueError`` naming ``name`` otherwise).
    """
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{name} must be MIN:MAX:STEP, got {text!r}")
    try:
        lo, hi, step = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"{name} must be three numbers MIN:MAX:STEP, got {text!r}") from None
    if not all(math.isfinite(v) for v in (lo, hi, step)):
        raise ValueError(f"{name} values must be finite, got {text!r}")
    if step <= 0:
        raise ValueError(f"{name} STEP must be > 0, got {step:g}")
    if hi < lo:
        raise ValueError(f"{name} is empty: MAX = {hi:g} < MIN = {lo:g}")
    count = (hi - lo) / step + 1e-9  # inf when MAX - MIN overflows or STEP underflows
    if not count < MAX_POINTS:
        raise ValueError(f"{name} {text!r} has more than {MAX_POINTS} points (allowed range "
                         f"[1, {MAX_POINTS}]): use a larger STEP")
    n = int(math.floor(count)) + 1
    values = lo + step * np.arange(n)
    # round off float noise (0.1 * 3 -> 0.3): at 1e-12, or finer for a very small STEP; a
    # value too large to round (x * 10**decimals overflows) is already exact enough
    decimals = max(12, 9 - math.floor(math.log10(step)))
    with np.errstate(all="ignore"):
        rounded = np.round(values, decimals)
    return _grid(np.where(np.isfinite(rounded), rounded, values), text, name)


def _min_max_count(parts: list[str], text: str, name: str) -> tuple[float, float, int]:
    """Finite ``MIN``, ``MAX`` and a count ``N >= 1`` from ``MIN:MAX:N`` pieces."""
    try:
        lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        raise ValueError(f"{name} must be MIN:MAX:N with N an integer, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} values must be finite, got {text!r}")
    if n < 1:
        raise ValueError(f"{name} is empty: N = {n} must be >= 1")
    if n > MAX_POINTS:
        raise ValueError(f"{name} N = {n} is outside the allowed range [1, {MAX_POINTS}]")
    return lo, hi, n


def parse_points(text: str, name: str) -> np.ndarray:
    """``MIN:MAX:N[:log|:lin]`` -> ``N`` points from MIN to MAX inclusive (default log)."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ValueError(f"{name} must be MIN:MAX:N[:log|:lin], got {text!r}")
    scale = parts[3] if len(parts) == 4 else "log"
    if scale not in ("log", "lin"):
        raise ValueError(f"{name} spacing must be log or lin, got {scale!r}")
    lo, hi, n = _min_max_count(parts[:3], text, name)
    if hi < lo:
        raise ValueError(f"{name} is inverted: MAX = {hi:g} < MIN = {lo:g}")
    if n == 1 and hi != lo:
        raise ValueError(f"{name}: N = 1 needs MIN = MAX, got {text!r}")
    if n > 1 and hi == lo:
        raise ValueError(f"{name}: MIN = MAX = {lo:g} with N = {n} repeats one value")
    if scale == "log" and lo <= 0:
        raise ValueError(f"{name} with log spacing needs MIN > 0, got {lo:g} "
                         "(use :lin for a range that starts at 0)")
    with np.errstate(all="ignore"):  # an overflow is reported by _grid, as one line
        values = np.geomspace(lo, hi, n) if scale == "log" else np.linspace(lo, hi, n)
    return _grid(values, text, name)


def parse_phases(text: str, name: str = "--phase") -> np.ndarray:
    """``MIN:MAX:N`` -> ``N`` points in [MIN, MAX) (MAX excluded: 0 and 2 pi are one phase)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{name} must be MIN:MAX:N, got {text!r}")
    lo, hi, n = _min_max_count(parts, text, name)
    if hi <= lo:
        raise ValueError(f"{name} is empty or inverted: MAX = {hi:g} <= MIN = {lo:g}")
    with np.errstate(all="ignore"):
        return _grid(lo + (hi - lo) * np.arange(n) / n, text, name)


def print_status_counts(status, meanings: dict, what: str = "cell(s)") -> None:
    """One line per non-zero status code: how many results have it and what it means
    (``meanings``: code -> text, e.g. :data:`jaxdea.STATUS`)."""
    status = np.asarray(status).ravel()
    codes, counts = np.unique(status[status != 0], return_counts=True)
    for k, n in zip(codes, counts):
        print(f"  {n} {what} with status {k}: {meanings.get(int(k), 'unknown')}")


def write_dataset(ds, out: Path) -> None:
    """Write NetCDF atomically (a temp file renamed into place), so an interrupted run never
    leaves a truncated file under the final name."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    ds = ds.assign_attrs(jaxdea_version=jaxdea_version())  # jaxdea's mark: it may replace it
    ds.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, out)


def check_writable(path: Path, name: str, directory_ok: bool = False) -> Path:
    """``path`` can be written, checked before any compute: it is not a directory (unless
    ``directory_ok``: a store that the writer replaces or resumes), and its nearest existing
    ancestor is a writable directory (missing folders are created when it is written).
    An existing file there must be one jaxdea wrote (:mod:`jaxdea.provenance`): a command
    replaces its own output, never a user's file. Raises ``ValueError`` naming the option
    otherwise."""
    if path.is_dir() and not directory_ok:
        raise ValueError(f"{name} {path} is a directory: give a file name")
    check_replaceable_file(path, name)
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"{name} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {path}: folder {parent} is not writable")
    return path


def netcdf_out(text: str) -> Path:
    """The ``--out`` path of a command that writes one NetCDF file (checked writable)."""
    out = Path(text)
    if out.suffix != ".nc":
        raise ValueError(f"--out must end in .nc (NetCDF), got {out}")
    return check_writable(out, "--out")


def check_png(text: str | None, name: str = "--plot", required: bool = False) -> None:
    """A PNG path argument (checked writable); unless ``required``, empty or None means no
    figure was asked for."""
    if (required or text) and not (text or "").endswith(".png"):
        raise ValueError(f"{name} must end in .png, got {text!r}")
    if text:
        check_writable(Path(text), name)


def protocol_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--protocol", default="paper", choices=["paper", "continuation", "periodic"],
                   help="paper: N cycles from rest per cell, mean of the last K; continuation: "
                        "the same, each f starting from the previous f's final state; periodic: "
                        "periodic steady state (settle, then Newton shooting)")
    p.add_argument("--direction", default="forward", choices=["forward", "backward"],
                   help="continuation: up (forward, as paper 000) or down the f axis")
    p.add_argument("--tol", type=float, default=1e-6,
                   help="periodic: tolerance on the scaled periodicity residual, (0, 1)")
    p.add_argument("--early-exit", type=early_exit, default=1e-8, metavar="TOL|off",
                   help="paper/continuation: stop a cell once its trajectory is periodic to TOL "
                        "(its remaining cycles would repeat the last one; default 1e-8); "
                        "'off' runs every cell for all N cycles")
    p.add_argument("--precision", default="double", choices=["double", "single"],
                   help="single: the lanes' states and the model in float32 (time, steps and "
                        "energy integrals stay float64), ~1.4x faster per step on CPU, within "
                        "1e-3 of double; paper/continuation only, with --early-exit off or "
                        ">= 1e-5")
    p.add_argument("--solver", default=StepControl().solver, choices=SOLVERS,
                   help="exponential: Krogstad's exponential RK4, ~2x more accurate at the same "
                        "--rtol, 5-15 %% slower (docs/models.md section 4)")
    p.add_argument("--extrapolate", type=tolerance_or_off("--extrapolate", auto=True),
                   default=StepControl().extrapolate, metavar="TOL|off|auto",
                   help="paper/continuation with an early exit: a cell whose slow transient "
                        "fits a linear recurrence of its cycle-start states to TOL jumps to a "
                        "few cycles before its averaged ones, where its early exit finds it "
                        "periodic (~1.3x faster maps, the same answers to ~1e-6); default auto: "
                        f"{EXTRAPOLATE:g} for jobs of {EXTRAPOLATE_FROM} cells or more, else off")


def tolerance_or_off(flag: str, auto: bool = False):
    """argparse type of ``flag``: a float, or ``None`` for 'off' / 'none', and with ``auto``
    'auto' itself (the range is the library's to check, naming the field)."""
    def parse(text: str) -> float | str | None:
        word = text.strip().lower()
        if word in ("off", "none"):
            return None
        if auto and word == AUTO:
            return AUTO
        try:
            return float(text)
        except ValueError:
            words = f", 'off' or {AUTO!r}" if auto else " or 'off'"
            raise argparse.ArgumentTypeError(
                f"{flag} must be a tolerance in (0, 1){words}, got {text!r}") from None
    return parse


early_exit = tolerance_or_off("--early-exit")


def lin_points(text: str, name: str) -> np.ndarray:
    """``MIN:MAX:N[:lin|:log]`` with linear spacing unless ``:log`` is given."""
    return parse_points(text + ":lin" if text.count(":") == 2 else text, name)
