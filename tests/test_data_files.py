"""Measured-data files a user gets slightly wrong: every mistake is one ``DataError`` line
naming the file, the column and the real line of the file, never a traceback or a silently
wrong number (``jaxdea.load_data``)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from jaxdea import DataError, FrequencyResponse, TimeSeries, load_data
from jaxdea.calibration.data import MAX_LENGTH, save_data

FR_HEAD = "# mass = 2 g\n# damping = 0.1 N s/m\n"


def _write(tmp_path: Path, text: str, name: str = "d.csv", bom: bool = False) -> Path:
    path = tmp_path / name
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


def _fails(path: Path, *patterns: str) -> str:
    with pytest.raises(DataError) as e:
        load_data(path)
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg, msg
    for pattern in patterns:
        assert re.search(pattern, msg), (pattern, msg)
    return msg


# ---- line numbers ---------------------------------------------------------------------------

# blank and comment lines before and between the rows: the bad row is on line 8 of the file
PADDED = "# measured 2024-05-01\n\nt [s],voltage [V],displacement [m]\n# run 1\n0,0,0\n\n" \
         "1,1,1e-3\n{bad}\n3,3,3e-3\n"


@pytest.mark.parametrize("bad, pattern", [
    ("2,x,2e-3", r"line 8, column 'voltage': 'x' is not a number"),
    ("2,,2e-3", r"line 8, column 'voltage': an empty cell"),
    ("2,2", r"line 8 has 2 fields, header has 3"),
    ("2,nan,2e-3", r"column 'voltage' has 1 non-finite value\(s\) \(first at row 2 \(line 8\)"),
    ("0.5,2,2e-3", r"not strictly increasing: row 2 \(line 8\)"),
    ("2,2,0.2", r"'displacement' reaches 0.2 m at row 2 \(line 8\)"),
    ("2,1_000,2e-3", r"line 8, column 'voltage': '1_000' is not a number"),
])
def test_row_errors_name_the_real_line(tmp_path, bad, pattern):
    _fails(_write(tmp_path, PADDED.format(bad=bad)), pattern)


def test_frequency_response_row_errors_name_the_real_line(tmp_path):
    text = FR_HEAD + "\nf [Hz],amplitude [mm]\n# sweep up\n10,0.1\n\n20,{a}\n{f},0.3\n"
    _fails(_write(tmp_path, text.format(a="-0.2", f="30")),
           r"'amplitude' must be >= 0 \(allowed range \[0, inf\) m\), got -0.0002 m at "
           r"row 1 \(line 8\)")
    _fails(_write(tmp_path, text.format(a="0.2", f="15")),
           r"not strictly increasing .* row 2 \(line 9\) \(f = 15 Hz\) follows f = 20 Hz")
    _fails(_write(tmp_path, text.format(a="0.2", f="0")),
           r"must be > 0 Hz \(allowed range \(0, inf\)\), got 0 Hz at row 2 \(line 9\)")
    _fails(_write(tmp_path, text.format(a="0.2", f="30") + "\n40;0.4\n"),
           r"line 11 has 1 fields, header has 2; .*seems to use ';'")


def test_header_errors_name_their_line(tmp_path):
    _fails(_write(tmp_path, FR_HEAD + "\nf [Hz],current [A]\n10,1\n"),
           r"line 4: unknown column 'current'")
    _fails(_write(tmp_path, "# x\nf [Hz],f [kHz]\n10,1\n"), r"line 2: column 'f' appears twice")
    _fails(_write(tmp_path, "f [Hz],amplitude [mm]\n# mass = 2 g\n# mass = 3 g\n"),
           r"line 3: '# mass' is given twice \(first on line 2\)")
    _fails(_write(tmp_path, "# mass = 2 g\n# damping = 0.1 N s/m\nf [Hz],mass [g],P_out [W]\n"
                            "10,2,1\n"), r"'mass' is given both as a column and on line 1")
    _fails(_write(tmp_path, "# mass = 2 g\n\n# damping = -1 N s/m\nf [Hz],P_out [W]\n10,1\n"),
           r"line 3: '# damping = -1 N s/m' is outside the allowed range \[0, inf\)")


# ---- encodings and separators ---------------------------------------------------------------

@pytest.mark.parametrize("head", ["", "# from Excel\n", "sep=,\n"])
def test_excel_utf8_bom_is_accepted(tmp_path, head):
    path = _write(tmp_path, head + "t [ms],voltage [kV],displacement [mm]\r\n0,0,0\r\n"
                  "10,1.5,0.2\r\n20,3,0.4\r\n", bom=True)
    d = load_data(path)
    assert isinstance(d, TimeSeries)
    np.testing.assert_allclose(d.t, [0, 0.01, 0.02])
    np.testing.assert_allclose(d.displacement, [0, 2e-4, 4e-4])


def test_not_utf8_is_one_clear_line(tmp_path):
    path = tmp_path / "d.csv"
    path.write_bytes("t [s],voltage [V],displacement [µm]\n0,0,0\n".encode("latin-1"))
    _fails(path, r"line 1: byte 0xb5 is not UTF-8 text; save the file as 'CSV UTF-8'")
    path.write_bytes("t [s],voltage [V]\n".encode("utf-16"))
    _fails(path, r"UTF-16")


@pytest.mark.parametrize("sep, said", [(";", "';'"), ("\t", "tabs")])
def test_semicolon_or_tab_separator_gets_a_hint(tmp_path, sep, said):
    text = sep.join(["f [Hz]", "amplitude [mm]"]) + "\n" + sep.join(["10", "0,1"]) + "\n"
    _fails(_write(tmp_path, FR_HEAD + text),
           rf"line 3: columns must be separated by commas; this file seems to use {said}")
    _fails(_write(tmp_path, "sep=;\n" + text), r"line 1: columns must be separated by commas")


# ---- ranges and units -----------------------------------------------------------------------

@pytest.mark.parametrize("column", ["amplitude", "P_out", "mass", "damping"])
def test_negative_values_are_rejected(tmp_path, column):
    cols = {"f": "Hz", "amplitude": "mm", "P_out": "mW", "mass": "g", "damping": "N s/m"}
    header = ",".join(f"{k} [{u}]" for k, u in cols.items())
    rows = ["10,0.1,1,2,0.1", "20,0.2,2,2,0.1"]
    bad = ["20", "0.2", "2", "2", "0.1"]
    bad[list(cols).index(column)] = "-0.5"
    text = header + "\n" + rows[0] + "\n\n" + ",".join(bad) + "\n"
    _fails(_write(tmp_path, text),
           rf"'{column}' must be >= 0 \(allowed range \[0, inf\) [^)]+\), got -0\.0*5 [^,]+ at "
           r"row 1 \(line 4\)$")


def test_negative_values_from_code_are_rejected_too():
    f = np.array([10.0, 20.0])
    with pytest.raises(DataError, match=r"'P_out' must be >= 0 .* at row 0$"):
        FrequencyResponse(f=f, mass=1e-3, damping=0.1, P_out=np.array([-1.0, 1.0]))
    with pytest.raises(DataError, match=r"'damping' must be >= 0 \(allowed range \[0, inf\)"):
        FrequencyResponse(f=f, mass=1e-3, damping=-0.1, P_out=np.array([1.0, 1.0]))


@pytest.mark.parametrize("column, kind", [("displacement", "ts"), ("amplitude", "fr")])
def test_millimetres_labelled_metres_are_caught(tmp_path, column, kind):
    if kind == "ts":
        text = "t [s],voltage [V],displacement [m]\n0,0,0\n1,1000,0.8\n2,2000,1.6\n"
    else:
        text = FR_HEAD + "f [Hz],amplitude [m]\n10,0.4\n20,1.2\n30,0.9\n"
    msg = _fails(_write(tmp_path, text),
                 rf"'{column}' reaches \S+ m at row \d \(line \d\), implausible for a DEA "
                 r"\(allowed magnitude up to 0.05 m\)",
                 r"look like mm \(or another smaller unit\) labelled as 'm'",
                 rf"fix the unit in the header, e\.g\. '{column} \[mm\]'")
    assert ("1.6 m" in msg) if kind == "ts" else ("1.2 m" in msg)
    # the same numbers with the right unit load, and so does a large but plausible stroke
    d = load_data(_write(tmp_path, text.replace(f"{column} [m]", f"{column} [mm]")))
    assert np.max(np.abs(getattr(d, column))) <= MAX_LENGTH
    load_data(_write(tmp_path, text.replace("0.8", "0.04").replace("1.6", "-0.049")
                     .replace("0.4", "0.01").replace("1.2", "0.049").replace("0.9", "0.02")))


def test_implausible_length_in_netcdf(tmp_path):
    f = np.array([10.0, 20.0])
    d = FrequencyResponse(f=f, mass=1e-3, damping=0.1, amplitude=np.array([0.3, 0.5]))
    _fails(save_data(d, tmp_path / "fr.nc"), r"'amplitude' reaches 0.5 m at row 1,",
           r"labelled as 'm'")


# ---- NetCDF ---------------------------------------------------------------------------------

def _good_nc(tmp_path: Path) -> Path:
    t = np.linspace(0, 1, 200)
    ts = TimeSeries(t=t, voltage=1e3 * t, displacement=1e-3 * t, force=t)
    return save_data(ts, tmp_path / "ts.nc")


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.99])
def test_truncated_netcdf_is_a_data_error(tmp_path, keep):
    raw = _good_nc(tmp_path).read_bytes()
    bad = tmp_path / "cut.nc"
    bad.write_bytes(raw[:int(keep * len(raw))])
    _fails(bad, r"cannot read as NetCDF")


@pytest.mark.parametrize("content", [b"", b"t [s],voltage [V]\n0,0\n", b"\x89HDF\r\n\x1a\n" +
                                     bytes(100), b"CDF\x01" + bytes(20)])
def test_non_netcdf_file_is_a_data_error(tmp_path, content):
    bad = tmp_path / "x.nc"
    bad.write_bytes(content)
    _fails(bad, r"cannot read as NetCDF")


def test_netcdf_oddities_are_data_errors(tmp_path):
    import xarray as xr

    f = np.array([10.0, 20.0])
    base = {"f": ("row", f, {"units": "Hz"}), "P_out": ("row", [1e-3, 2e-3], {"units": "W"})}
    xr.Dataset(base, attrs={"mass": "2 g", "damping": 0.1}).to_netcdf(tmp_path / "a.nc")
    _fails(tmp_path / "a.nc", r"attribute 'mass' = '2 g' must be a number")
    xr.Dataset({**base, "amplitude": ("row", ["a", "b"], {"units": "m"})},
               attrs={"mass": 1e-3, "damping": 0.1}).to_netcdf(tmp_path / "b.nc")
    _fails(tmp_path / "b.nc", r"column 'amplitude' must hold numbers")
    xr.Dataset({"f": ("row", f, {"units": 3.0}), "P_out": base["P_out"]},
               attrs={"mass": 1e-3, "damping": 0.1}).to_netcdf(tmp_path / "c.nc")
    _fails(tmp_path / "c.nc", r"the unit of 'f' must be text \(allowed: Hz, kHz\), got 3.0")


def test_netcdf3_file_loads(tmp_path):
    import xarray as xr

    t = np.linspace(0, 1, 5)
    ds = xr.Dataset({"t": ("t", t, {"units": "s"}), "voltage": ("t", t, {"units": "kV"}),
                     "displacement": ("t", t, {"units": "mm"})})
    ds.to_netcdf(tmp_path / "classic.nc", engine="scipy")
    d = load_data(tmp_path / "classic.nc")
    np.testing.assert_allclose(d.voltage, 1e3 * t)


def test_folder_named_like_a_data_file(tmp_path):
    (tmp_path / "dir.csv").mkdir()
    _fails(tmp_path / "dir.csv", r"is a folder")


@pytest.mark.parametrize("at", [0.01, 0.71])
def test_damaged_netcdf_is_one_quiet_data_error(tmp_path, at):
    """Overwritten metadata: a DataError, and no 'Exception ignored' noise from the reader."""
    import gc
    import sys

    raw = bytearray(_good_nc(tmp_path).read_bytes())
    i = int(at * len(raw))
    raw[i:i + 64] = b"\xff" * 64
    bad = tmp_path / "damaged.nc"
    bad.write_bytes(bytes(raw))
    noise = []
    hook, sys.unraisablehook = sys.unraisablehook, noise.append
    try:
        try:
            load_data(bad)
        except DataError as e:
            assert str(bad) in str(e) and "\n" not in str(e)
        gc.collect()
    finally:
        sys.unraisablehook = hook
    assert not noise, [n.exc_value for n in noise]
