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
``# mass = 2 g`` or ``# damping = 0.1 N s/m``. NetCDF: variables (or coordinates) with those
names and a ``units`` attribute; file-wide values as attributes ``mass``/``damping`` (SI, or
with ``mass_units`` etc.). Units are converted to SI from the table :data:`UNITS`; a unit that
does not measure the column's quantity (e.g. ``displacement [V]``) is rejected.
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


def _si(name: str, unit: str, where: str) -> float:
    table = UNITS.get(name)
    if table is None:
        raise DataError(f"{where}: unknown column {name!r}")
    unit = unit.strip()
    if not unit:
        raise DataError(f"{where}: column {name!r} has no unit; write it as "
                        f"'{name} [{SI_UNITS[name]}]' (allowed units: {', '.join(table)})")
    if unit not in table:
        raise DataError(f"{where}: column {name!r} has unit {unit!r}, which does not measure "
                        f"{name}; allowed units: {', '.join(table)}")
    return table[unit]


def _finite(name: str, values: np.ndarray, where: str) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DataError(f"{where}: column {name!r} has {int(bad.sum())} non-finite value(s) "
                        f"(first at row {i}: {v.flat[i]!r}); remove or fill them")
    return v


@dataclass(frozen=True)
class TimeSeries:
    """A transient experiment (SI): drive ``voltage(t)``, measured ``displacement(t)``
    [, ``force(t)``]. ``t`` strictly increasing; ``attrs`` keeps file metadata."""

    t: np.ndarray
    voltage: np.ndarray
    displacement: np.ndarray
    force: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    source: str = "<data>"

    def __post_init__(self):
        where = self.source
        n = None
        for name in TIME_COLUMNS:
            v = getattr(self, name)
            if v is None:
                if name != "force":
                    raise DataError(f"{where}: missing column {name!r}; a time series needs "
                                    "t, voltage, displacement (force optional)")
                continue
            v = _finite(name, np.atleast_1d(np.asarray(v, dtype=float)), where)
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
            raise DataError(f"{where}: time 't' is not strictly increasing: row {i + 1} "
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
    ``f``, with that row's payload ``mass`` and ``damping``."""

    f: np.ndarray
    mass: np.ndarray
    damping: np.ndarray
    amplitude: np.ndarray | None = None
    P_out: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    source: str = "<data>"

    def __post_init__(self):
        where = self.source
        f = _finite("f", np.atleast_1d(np.asarray(self.f, dtype=float)), where)
        if f.ndim != 1 or f.size < 1:
            raise DataError(f"{where}: column 'f' must be a non-empty 1-D array")
        if np.any(f <= 0):
            raise DataError(f"{where}: frequencies 'f' must be > 0 Hz, got min {f.min():g}")
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
            v = _finite(name, np.asarray(v, dtype=float), where)
            if v.ndim == 0:
                v = np.full(f.shape, float(v))
            if v.shape != f.shape:
                raise DataError(f"{where}: column {name!r} has {v.size} rows, f has {f.size}")
            if name in ("mass", "damping") and np.any(v < 0):
                raise DataError(f"{where}: {name!r} must be >= 0, got min {v.min():g}")
            object.__setattr__(self, name, v)
        for (m, c), idx in self.groups().items():
            if not np.all(np.diff(f[idx]) > 0):
                raise DataError(f"{where}: frequencies 'f' are not strictly increasing for the "
                                f"payload mass = {m:g} kg, damping = {c:g} N s/m")

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


def _read_csv(path: Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    where = str(path)
    meta: dict[str, float] = {}
    with path.open(newline="") as fh:
        lines = fh.read().splitlines()
    body = []
    for line in lines:
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = _META.match(s)
            if m and m.group(1) in ("mass", "damping"):
                name, value, unit = m.groups()
                try:
                    v = float(value)
                except ValueError:
                    raise DataError(f"{where}: '# {name} = {value}' is not a number") from None
                meta[name] = v * _si(name, unit, where)
            continue
        body.append(line)
    if not body:
        raise DataError(f"{where}: no header row (expected e.g. 't [s],voltage [V],...')")
    rows = list(csv.reader(body))
    header, data = rows[0], rows[1:]
    names, factors = [], []
    for col in header:
        m = _HEADER.match(col)
        if not m:
            raise DataError(f"{where}: cannot read column header {col!r}; write 'name [unit]'")
        name, unit = m.group(1), m.group(2) or ""
        if name not in UNITS:
            raise DataError(f"{where}: unknown column {name!r}; allowed: {', '.join(UNITS)}")
        if name in names:
            raise DataError(f"{where}: column {name!r} appears twice")
        names.append(name)
        factors.append(_si(name, unit, where))
    if not data:
        raise DataError(f"{where}: header but no data rows")
    cols: dict[str, list[float]] = {n: [] for n in names}
    for r, row in enumerate(data, start=2):
        if len(row) != len(names):
            raise DataError(f"{where}: line {r} has {len(row)} fields, header has {len(names)}")
        for n, cell in zip(names, row):
            try:
                cols[n].append(float(cell))
            except ValueError:
                raise DataError(f"{where}: line {r}, column {n!r}: {cell!r} is not a number"
                                ) from None
    return {n: np.asarray(v) * k for (n, v), k in zip(cols.items(), factors)}, meta


def _read_netcdf(path: Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    import xarray as xr

    where = str(path)
    try:
        ds = xr.open_dataset(path, engine="h5netcdf")
    except Exception as exc:  # noqa: BLE001 - any reader failure is a data error
        raise DataError(f"{where}: cannot read as NetCDF: {exc}") from None
    with ds:
        cols = {}
        for name in UNITS:
            if name in ds.variables:
                var = ds[name]
                unit = var.attrs.get("units")
                if unit is None:
                    raise DataError(f"{where}: variable {name!r} has no 'units' attribute "
                                    f"(allowed: {', '.join(UNITS[name])})")
                cols[name] = np.asarray(var.values, dtype=float).ravel() * _si(name, unit, where)
        meta = {}
        for name in ("mass", "damping"):
            if name in ds.attrs and name not in cols:
                unit = ds.attrs.get(f"{name}_units", SI_UNITS[name])
                meta[name] = float(ds.attrs[name]) * _si(name, unit, where)
    return cols, meta


def load_data(path: str | Path) -> Data:
    """Read and validate a measured data file (``.csv`` or ``.nc``): a :class:`TimeSeries` if
    it has a ``t`` column, a :class:`FrequencyResponse` if it has ``f``."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"data file not found: {path}")
    if path.suffix.lower() == ".csv":
        cols, meta = _read_csv(path)
    elif path.suffix.lower() in (".nc", ".nc4", ".netcdf"):
        cols, meta = _read_netcdf(path)
    else:
        raise DataError(f"{path}: unknown data format {path.suffix!r}; use .csv or .nc")
    return data_from_columns(cols, meta, source=str(path))


def data_from_columns(cols: dict[str, np.ndarray], meta: dict[str, float] | None = None,
                      source: str = "<data>") -> Data:
    """Build the right data class from SI columns (and file-wide ``mass``/``damping``)."""
    meta = dict(meta or {})
    if "t" in cols and "f" in cols:
        raise DataError(f"{source}: has both 't' and 'f' columns; a file holds one kind of data")
    if "t" in cols:
        extra = sorted(set(cols) - set(TIME_COLUMNS))
        if extra:
            raise DataError(f"{source}: column(s) {', '.join(extra)} do not belong in a time "
                            f"series (t, voltage, displacement, force)")
        return TimeSeries(**{k: cols.get(k) for k in TIME_COLUMNS}, source=source)
    if "f" in cols:
        extra = sorted(set(cols) - set(FREQ_COLUMNS))
        if extra:
            raise DataError(f"{source}: column(s) {', '.join(extra)} do not belong in a "
                            "frequency response (f, amplitude, P_out, mass, damping)")
        kw = {k: cols.get(k, meta.get(k)) for k in ("mass", "damping")}
        return FrequencyResponse(f=cols["f"], amplitude=cols.get("amplitude"),
                                 P_out=cols.get("P_out"), **kw, source=source)
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
