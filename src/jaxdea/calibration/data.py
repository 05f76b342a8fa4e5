"""Measured data for calibration: time series and frequency responses, from CSV or NetCDF.

Two kinds of data set, both validated on load (every problem raises :class:`DataError` naming
the file, the column and what is wrong):

- :class:`TimeSeries`: ``t`` (s, strictly increasing), ``voltage`` (V), ``displacement`` (m)
  and optionally ``force`` (N), all finite. The transient experiments of papers 001/002.
- :class:`FrequencyResponse`: ``f`` (Hz, > 0) with ``amplitude`` (m) and/or ``P_out`` (W), plus
  the payload ``mass`` (kg) and ``damping`` (N s/m) of each row (a column, or one value for the
  whole file). Within one payload ``f`` must be strictly increasing. The sweeps of paper 000.

File formats
------------
CSV: one header row naming every column *with its unit in brackets*, e.g.
``t [s],voltage [kV],displacement [mm]``; ``#`` lines before it may give file-wide values as
``# mass = 2 g`` or ``# damping = 0.1 N s/m``; blank lines and other ``#`` lines are skipped.
Columns are separated by commas (a file with ``;`` or tab separators gets a hint); the file is
UTF-8, with or without the byte-order mark that Excel's "CSV UTF-8" writes. Every message about
a row names its 1-based line in the file. NetCDF: variables (or coordinates) with those names
and a ``units`` attribute; file-wide values as attributes ``mass``/``damping`` (SI, or with
``mass_units`` etc.); a damaged or non-NetCDF file is a :class:`DataError`, too. Units are
converted to SI from the table :data:`UNITS`; a unit that does not measure the column's
quantity (e.g. ``displacement [V]``) is rejected.

Ranges: ``amplitude``, ``P_out``, ``mass``, ``damping`` >= 0 (allowed range ``[0, inf)``).
A file's ``displacement`` or ``amplitude`` may not exceed :data:`MAX_LENGTH` = 5 cm in
magnitude: a DEA's stroke is millimetres (papers 000-002: a few mm; the planar DEA of 004:
about 1 cm), so a larger value is taken as a unit slip (mm under a ``[m]`` header) and rejected.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._checks import DataError

#: Accepted units per quantity -> factor to SI.
_LENGTH = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
UNITS: dict[str, dict[str, float]] = {
    "t": {"s": 1.0, "ms": 1e-3},
    "voltage": {"V": 1.0, "kV": 1e3},
    "displacement": _LENGTH,
    "force": {"N": 1.0, "mN": 1e-3},
    "f": {"Hz": 1.0, "kHz": 1e3},
    "amplitude": _LENGTH,
    "P_out": {"W": 1.0, "mW": 1e-3, "uW": 1e-6, "µW": 1e-6},
    "mass": {"kg": 1.0, "g": 1e-3},
    "damping": {"N s/m": 1.0, "Ns/m": 1.0, "N*s/m": 1.0, "kg/s": 1.0},
}
SI_UNITS = {k: next(iter(v)) for k, v in UNITS.items()}

TIME_COLUMNS = ("t", "voltage", "displacement", "force")
FREQ_COLUMNS = ("f", "amplitude", "P_out", "mass", "damping")
#: Largest plausible |displacement| or |amplitude| in a data file, m (5 cm; see above).
MAX_LENGTH = 0.05


def _si(name: str, unit: Any, where: str) -> float:
    table = UNITS.get(name)
    if table is None:
        raise DataError(f"{where}: unknown column {name!r}")
    if not isinstance(unit, str):
        raise DataError(f"{where}: the unit of {name!r} must be text (allowed: "
                        f"{', '.join(table)}), got {np.asarray(unit).tolist()!r}")
    unit = unit.strip()
    if not unit:
        raise DataError(f"{where}: column {name!r} has no unit; write it as "
                        f"'{name} [{SI_UNITS[name]}]' (allowed units: {', '.join(table)})")
    if unit not in table:
        raise DataError(f"{where}: column {name!r} has unit {unit!r}, which does not measure "
                        f"{name}; allowed units: {', '.join(table)}")
    return table[unit]


def _at(lines: np.ndarray | None, i: int) -> str:
    """Row ``i`` of the data, with its 1-based line in the file when read from one."""
    if lines is not None and 0 <= i < len(lines):
        return f"row {i} (line {int(lines[i])})"
    return f"row {i}"


def _finite(name: str, values: Any, where: str, lines: np.ndarray | None = None) -> np.ndarray:
    try:
        v = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise DataError(f"{where}: column {name!r} must hold numbers") from None
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DataError(f"{where}: column {name!r} has {int(bad.sum())} non-finite value(s) "
                        f"(first at {_at(lines, i)}: {float(v.flat[i])!r}); remove or fill them")
    return v


@dataclass(frozen=True)
class TimeSeries:
    """A transient experiment (SI): drive ``voltage(t)``, measured ``displacement(t)``
    [, ``force(t)``]. ``t`` strictly increasing; ``attrs`` keeps file metadata; ``lines``
    (optional) the 1-based file line of each row, named in error messages."""

    t: np.ndarray
    voltage: np.ndarray
    displacement: np.ndarray
    force: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    source: str = "<data>"
    lines: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        where, lines = self.source, self.lines
        n = None
        for name in TIME_COLUMNS:
            v = getattr(self, name)
            if v is None:
                if name != "force":
                    raise DataError(f"{where}: missing column {name!r}; a time series needs "
                                    "t, voltage, displacement (force optional)")
                continue
            v = np.atleast_1d(_finite(name, v, where, lines))
            if v.ndim != 1:
                raise DataError(f"{where}: column {name!r} must be 1-D, got shape {v.shape}")
            if n is not None and v.size != n:
                raise DataError(f"{where}: column {name!r} has {v.size} rows, t has {n}")
            n = v.size
            object.__setattr__(self, name, v)
        if n < 3:
            raise DataError(f"{where}: a time series needs at least 3 samples, got {n}")
        dt = np.diff(self.t)
        if not np.all(dt > 0):
            i = int(np.flatnonzero(dt <= 0)[0])
            raise DataError(f"{where}: time 't' is not strictly increasing: {_at(lines, i + 1)} "
                            f"(t = {self.t[i + 1]:g} s) follows t = {self.t[i]:g} s")

    @property
    def channels(self) -> dict[str, np.ndarray]:
        """The measured outputs a model is fitted to."""
        out = {"displacement": self.displacement}
        if self.force is not None:
            out["force"] = self.force
        return out


@dataclass(frozen=True)
class FrequencyResponse:
    """Steady-state response over frequency (SI): ``amplitude`` and/or ``P_out`` at each
    ``f``, with that row's payload ``mass`` and ``damping`` (all four >= 0); ``lines``
    (optional) the 1-based file line of each row, named in error messages."""

    f: np.ndarray
    mass: np.ndarray
    damping: np.ndarray
    amplitude: np.ndarray | None = None
    P_out: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    source: str = "<data>"
    lines: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        where, lines = self.source, self.lines
        f = np.atleast_1d(_finite("f", self.f, where, lines))
        if f.ndim != 1 or f.size < 1:
            raise DataError(f"{where}: column 'f' must be a non-empty 1-D array")
        if np.any(f <= 0):
            i = int(np.flatnonzero(f <= 0)[0])
            raise DataError(f"{where}: frequencies 'f' must be > 0 Hz (allowed range (0, inf)), "
                            f"got {f[i]:g} Hz at {_at(lines, i)}")
        object.__setattr__(self, "f", f)
        if self.amplitude is None and self.P_out is None:
            raise DataError(f"{where}: missing column: a frequency response needs 'amplitude' "
                            "and/or 'P_out'")
        for name in ("mass", "damping", "amplitude", "P_out"):
            v = getattr(self, name)
            if v is None:
                if name in ("mass", "damping"):
                    raise DataError(f"{where}: missing {name!r}: give a column or a file-wide "
                                    f"value ('# {name} = ... {SI_UNITS[name]}')")
                continue
            v = _finite(name, v, where, lines)
            if v.ndim == 0:
                if v < 0:
                    raise DataError(f"{where}: {name!r} must be >= 0 (allowed range [0, inf) "
                                    f"{SI_UNITS[name]}), got {float(v):g}")
                v = np.full(f.shape, float(v))
            if v.shape != f.shape:
                raise DataError(f"{where}: column {name!r} has {v.size} rows, f has {f.size}")
            if np.any(v < 0):
                i = int(np.flatnonzero(v < 0)[0])
                raise DataError(f"{where}: {name!r} must be >= 0 (allowed range [0, inf) "
                                f"{SI_UNITS[name]}), got {v[i]:g} {SI_UNITS[name]} at "
                                f"{_at(lines, i)}")
            object.__setattr__(self, name, v)
        for (m, c), idx in self.groups().items():
            bad = np.flatnonzero(np.diff(f[idx]) <= 0)
            if bad.size:
                i = int(idx[bad[0] + 1])
                raise DataError(f"{where}: frequencies 'f' are not strictly increasing for the "
                                f"payload mass = {m:g} kg, damping = {c:g} N s/m: "
                                f"{_at(lines, i)} (f = {f[i]:g} Hz) follows "
                                f"f = {f[idx[bad[0]]]:g} Hz")

    def groups(self) -> dict[tuple[float, float], np.ndarray]:
        """Row indices of each payload ``(mass, damping)``, in order of first appearance."""
        out: dict[tuple[float, float], list[int]] = {}
        for i, key in enumerate(zip(self.mass.tolist(), self.damping.tolist())):
            out.setdefault(key, []).append(i)
        return {k: np.asarray(v) for k, v in out.items()}

    @property
    def channels(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("amplitude", "P_out") if getattr(self, k) is not None}

    @classmethod
    def from_sweep(cls, ds, channels=("amplitude", "P_out")) -> FrequencyResponse:
        """From a :func:`jaxdea.sweep` Dataset (payload from its attrs)."""
        kw = {k: np.asarray(ds[k].values, dtype=float) for k in channels}
        f = np.asarray(ds["f"].values, dtype=float)
        return cls(f=f, mass=np.full(f.shape, float(ds.attrs["mass"])),
                   damping=np.full(f.shape, float(ds.attrs["damping"])), **kw,
                   source="<sweep dataset>")


Data = TimeSeries | FrequencyResponse

_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[(.*)\])?\s*$")
_META = re.compile(r"^#\s*([A-Za-z_]+)\s*=\s*([^\s]+)\s*(.*)$")
_SEPARATORS = {";": "';'", "\t": "tabs"}

#: A reader's output: SI columns, file-wide values, units as written, 1-based row lines or None.
Columns = tuple[dict[str, np.ndarray], dict[str, float], dict[str, str], np.ndarray | None]


def _decode(path: Path) -> str:
    """The text of ``path``: UTF-8, with or without a byte-order mark."""
    where = str(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{where}: cannot read the file: {exc.strerror or exc}") from None
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise DataError(f"{where}: the file is UTF-16 text; save it as 'CSV UTF-8'")
    raw = raw.removeprefix(b"\xef\xbb\xbf")  # as encoding="utf-8-sig": Excel's "CSV UTF-8"
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise DataError(f"{where}: line {line}: byte {raw[exc.start]:#04x} is not UTF-8 text; "
                        "save the file as 'CSV UTF-8'") from None


def _split(line: str, n: int, where: str) -> list[str]:
    try:
        return next(csv.reader([line]))
    except csv.Error as exc:
        raise DataError(f"{where}: line {n}: cannot split into columns ({exc})") from None


def _separator_hint(line: str) -> str:
    """A hint naming the separator ``line`` seems to use instead of commas ('' if none)."""
    said = next((said for sep, said in _SEPARATORS.items() if sep in line), "")
    return said and (f"columns must be separated by commas; this file seems to use {said} "
                     "(save as comma-separated CSV, with '.' as the decimal point)")


def _number(cell: str, n: int, name: str, where: str) -> float:
    text = cell.strip()
    try:
        return float(text.replace("_", "x"))  # float() reads 1_000; a CSV cell does not
    except ValueError:
        what = "an empty cell" if not text else f"{cell!r} is not a number"
        raise DataError(f"{where}: line {n}, column {name!r}: {what}") from None


def _meta_line(text: str, n: int, meta: dict, seen: dict[str, int], where: str) -> None:
    """Read a ``# mass = 2 g`` / ``# damping = 0.1 N s/m`` line into ``meta`` (SI)."""
    m = _META.match(text)
    if not (m and m.group(1) in ("mass", "damping")):
        return  # any other comment
    name, value, unit = m.groups()
    if name in seen:
        raise DataError(f"{where}: line {n}: '# {name}' is given twice (first on line "
                        f"{seen[name]}); keep one")
    try:
        v = float(value) * _si(name, unit, where)
    except ValueError:
        raise DataError(f"{where}: line {n}: '# {name} = {value}' is not a number; write e.g. "
                        f"'# {name} = 0.1 {SI_UNITS[name]}'") from None
    if not (np.isfinite(v) and v >= 0):
        raise DataError(f"{where}: line {n}: '# {name} = {value} {unit}' is outside the "
                        f"allowed range [0, inf) {SI_UNITS[name]}")
    meta[name], seen[name] = v, n


def _read_csv(path: Path) -> Columns:
    where = str(path)
    meta, seen = {}, {}  # name -> SI value, name -> its line
    header: tuple[int, str] | None = None
    body: list[tuple[int, str]] = []
    for n, line in enumerate(re.split(r"\r\n|\r|\n", _decode(path)), start=1):
        s = line.strip()
        if s.startswith("#"):
            _meta_line(s, n, meta, seen, where)
        elif not s or (header is None and s.replace(" ", "").lower() == "sep=,"):
            continue  # a blank line, or Excel's separator line
        elif header is None:
            header = (n, line)
        else:
            body.append((n, line))
    if header is None:
        raise DataError(f"{where}: no header row (expected e.g. 't [s],voltage [V],...')")
    n, line = header
    cells = _split(line, n, where)
    if (len(cells) == 1 or line.lower().startswith("sep=")) and _separator_hint(line):
        raise DataError(f"{where}: line {n}: {_separator_hint(line)}")
    names, factors, units = [], [], {}
    for col in cells:
        m = _HEADER.match(col)
        if not m:
            raise DataError(f"{where}: line {n}: cannot read column header {col!r}; "
                            "write 'name [unit]'")
        name, unit = m.group(1), m.group(2) or ""
        if name not in UNITS:
            raise DataError(f"{where}: line {n}: unknown column {name!r}; allowed: "
                            f"{', '.join(UNITS)}")
        if name in names:
            raise DataError(f"{where}: line {n}: column {name!r} appears twice")
        names.append(name)
        factors.append(_si(name, unit, where))
        units[name] = unit.strip()
    clash = sorted(set(meta) & set(names))
    if clash:
        raise DataError(f"{where}: {clash[0]!r} is given both as a column and on line "
                        f"{seen[clash[0]]} ('# {clash[0]} = ...'); keep one")
    if not body:
        raise DataError(f"{where}: header but no data rows")
    cols: dict[str, list[float]] = {name: [] for name in names}
    for n, line in body:
        row = _split(line, n, where)
        if len(row) != len(names):
            hint = _separator_hint(line)
            raise DataError(f"{where}: line {n} has {len(row)} fields, header has {len(names)}"
                            + (f"; {hint}" if hint else ""))
        for name, cell in zip(names, row):
            cols[name].append(_number(cell, n, name, where))
    with np.errstate(over="ignore", invalid="ignore"):
        si = {name: np.asarray(v) * k for (name, v), k in zip(cols.items(), factors)}
    return si, meta, units, np.asarray([n for n, _ in body])


def _open_netcdf(path: Path):
    import h5py
    import xarray as xr

    opts = {"decode_times": False, "decode_timedelta": False}
    with path.open("rb") as fh:
        if fh.read(3) == b"CDF":  # NetCDF-3 (classic), which h5netcdf cannot read
            return xr.open_dataset(path, engine="scipy", **opts)
    with h5py.File(path, "r") as fh:  # a damaged file fails here, not in h5netcdf (whose
        fh.visititems(lambda _, obj: dict(obj.attrs) and None)  # half-open File is noisy)
    return xr.open_dataset(path, engine="h5netcdf", **opts)


def _read_netcdf(path: Path) -> Columns:
    where = str(path)
    cols, meta, units = {}, {}, {}
    try:
        with _open_netcdf(path) as ds:
            for name in (n for n in UNITS if n in ds.variables):
                unit = ds[name].attrs.get("units")
                if unit is None:
                    raise DataError(f"{where}: variable {name!r} has no 'units' attribute "
                                    f"(allowed: {', '.join(UNITS[name])})")
                values = _finite(name, ds[name].values, where).ravel()
                with np.errstate(over="ignore"):
                    cols[name], units[name] = values * _si(name, unit, where), str(unit).strip()
            for name in ("mass", "damping"):
                if name in ds.attrs and name not in cols:
                    try:
                        value = float(ds.attrs[name])
                    except (TypeError, ValueError):
                        raise DataError(f"{where}: attribute {name!r} = {ds.attrs[name]!r} must "
                                        f"be a number (unit in '{name}_units')") from None
                    unit = ds.attrs.get(f"{name}_units", SI_UNITS[name])
                    meta[name] = value * _si(name, unit, where)
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign file, whatever the reader
        detail = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise DataError(f"{where}: cannot read as NetCDF ({detail}); is it a complete "
                        "NetCDF file?") from None
    return cols, meta, units, None


def _check_lengths(data: Data, units: dict[str, str], where: str) -> None:
    """A ``displacement``/``amplitude`` above :data:`MAX_LENGTH` is a unit slip (see top)."""
    for name in ("displacement", "amplitude"):
        v = getattr(data, name, None)
        if v is None or not np.any(np.abs(v) > MAX_LENGTH):
            continue
        i = int(np.argmax(np.abs(v)))
        unit = units.get(name, "m")
        raise DataError(
            f"{where}: column {name!r} reaches {v[i]:g} m at {_at(data.lines, i)}, implausible "
            f"for a DEA (allowed magnitude up to {MAX_LENGTH:g} m); the values look like mm "
            f"(or another smaller unit) labelled as {unit!r}: fix the unit in the header, e.g. "
            f"'{name} [mm]'")


def load_data(path: str | Path) -> Data:
    """Read and validate a measured data file (``.csv`` or ``.nc``; see the module docstring).

    Arguments:
        path: the file.

    Returns:
        A :class:`TimeSeries` if it has a ``t`` column, a :class:`FrequencyResponse` if it has
        ``f`` (SI units). Every problem raises :class:`DataError` naming the file, the column
        and, for a CSV row, its 1-based line.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"data file not found: {path}")
    if path.is_dir():
        raise DataError(f"{path} is a folder, not a data file")
    if path.suffix.lower() == ".csv":
        cols, meta, units, lines = _read_csv(path)
    elif path.suffix.lower() in (".nc", ".nc4", ".netcdf"):
        cols, meta, units, lines = _read_netcdf(path)
    else:
        raise DataError(f"{path}: unknown data format {path.suffix!r}; use .csv or .nc")
    data = data_from_columns(cols, meta, source=str(path), lines=lines)
    _check_lengths(data, units, str(path))
    return data


def data_from_columns(cols: dict[str, np.ndarray], meta: dict[str, float] | None = None,
                      source: str = "<data>", lines: np.ndarray | None = None) -> Data:
    """Build the right data class from SI columns (and file-wide ``mass``/``damping``).

    Arguments:
        cols: column name -> SI values.
        meta: file-wide ``mass``/``damping`` (SI), used where there is no such column.
        source: the name errors give (a file path).
        lines: the 1-based file line of each row, named in errors (optional).

    Returns:
        A :class:`TimeSeries` (``t`` column) or :class:`FrequencyResponse` (``f`` column).
    """
    meta = dict(meta or {})
    if "t" in cols and "f" in cols:
        raise DataError(f"{source}: has both 't' and 'f' columns; a file holds one kind of data")
    if "t" in cols:
        extra = sorted(set(cols) - set(TIME_COLUMNS))
        if extra:
            raise DataError(f"{source}: column(s) {', '.join(extra)} do not belong in a time "
                            f"series (t, voltage, displacement, force)")
        return TimeSeries(**{k: cols.get(k) for k in TIME_COLUMNS}, source=source, lines=lines)
    if "f" in cols:
        extra = sorted(set(cols) - set(FREQ_COLUMNS))
        if extra:
            raise DataError(f"{source}: column(s) {', '.join(extra)} do not belong in a "
                            "frequency response (f, amplitude, P_out, mass, damping)")
        kw = {k: cols.get(k, meta.get(k)) for k in ("mass", "damping")}
        return FrequencyResponse(f=cols["f"], amplitude=cols.get("amplitude"),
                                 P_out=cols.get("P_out"), **kw, source=source, lines=lines)
    raise DataError(f"{source}: missing column: need 't' (time series) or 'f' (frequency "
                    f"response); found {', '.join(cols) or 'none'}")


def save_data(data: Data, path: str | Path) -> Path:
    """Write ``data`` as CSV (SI units in the header) or NetCDF (``units`` attributes)."""
    path = Path(path)
    if isinstance(data, TimeSeries):
        names = [n for n in TIME_COLUMNS if getattr(data, n) is not None]
    else:
        names = ["f", "mass", "damping"] + list(data.channels)
    cols = {n: np.asarray(getattr(data, n)) for n in names}
    if path.suffix.lower() == ".csv":
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow([f"{n} [{SI_UNITS[n]}]" for n in names])
            for row in zip(*cols.values()):
                w.writerow([repr(float(v)) for v in row])
    elif path.suffix.lower() == ".nc":
        import xarray as xr

        dim = "t" if isinstance(data, TimeSeries) else "row"
        ds = xr.Dataset({n: xr.Variable((dim,), v, {"units": SI_UNITS[n]})
                         for n, v in cols.items()})
        ds.to_netcdf(path, engine="h5netcdf")
    else:
        raise DataError(f"{path}: unknown data format {path.suffix!r}; use .csv or .nc")
    return path
