"""Property-based tests (hypothesis): a user's mistake raises a ``jaxdea.JaxdeaError`` (or, for
the CLI's range parsers, a ``ValueError`` the CLI turns into one line), never another
exception and never a silently wrong number.

Mutated inputs: every config family in ``configs/`` (``model_from_dict``), calibration CSVs
(``load_data``) and the ``MIN:MAX:STEP`` / ``MIN:MAX:N`` command-line ranges. The example
counts are bounded and the runs derandomized, so the file is reproducible and quick (about
30 s on 2 cores).
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
import re
import tempfile
import tomllib
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, event, example, given, settings
from hypothesis import strategies as st

import jaxdea
from jaxdea.calibration.data import UNITS
from jaxdea.cli import main
from jaxdea.cli.args import lin_points, parse_phases, parse_points, parse_range
from jaxdea.config import LOADERS

CONFIG_DIR = Path(__file__).parents[1] / "configs"
CONFIGS = {p.stem: tomllib.loads(p.read_text()) for p in sorted(CONFIG_DIR.glob("*.toml"))}


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow,
                                           HealthCheck.function_scoped_fixture])


# ---- values a user might type -------------------------------------------------------------

ODD_FLOATS = st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, -0.0, 1e308, -1e308,
                              5e-324, 1e-300, 1e300, 1.0, 2.0, 0.5])
NUMBERS = st.one_of(ODD_FLOATS, st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(-10**400, 10**400), st.integers(-3, 3))
SCALARS = st.one_of(NUMBERS, st.text(max_size=6), st.booleans())
VALUES = st.one_of(
    NUMBERS,
    st.text(max_size=8),
    st.sampled_from(["equilibrium", "weight", "frozen", "literal", "1.0", "nan", ""]),
    st.booleans(),
    st.lists(SCALARS, max_size=5),
    st.lists(NUMBERS, min_size=1, max_size=5),
    st.dictionaries(st.text(max_size=4), SCALARS, max_size=3),
    st.just({}),
    st.just([]),
)


def _paths(node, prefix=()):
    """Every path (keys and list indices) inside a parsed TOML document."""
    items = node.items() if isinstance(node, dict) else enumerate(node)
    for k, v in items:
        yield (*prefix, k)
        if isinstance(v, dict | list):
            yield from _paths(v, (*prefix, k))


def _parent(cfg, path):
    node = cfg
    for k in path[:-1]:
        node = node[k]
    return node


SCALES = st.sampled_from([-1.0, 0.0, 1e-6, 0.1, 0.3, 0.5, 0.9, 1.1, 2.0, 3.0, 10.0, 1e6])


def _is_number(value) -> bool:
    """A TOML number (a 64-bit integer or a float)."""
    return isinstance(value, float) or (isinstance(value, int) and not isinstance(value, bool)
                                        and abs(value) < 2**63)


@st.composite
def mutated_configs(draw):
    name = draw(st.sampled_from(sorted(CONFIGS)))
    cfg = copy.deepcopy(CONFIGS[name])
    for _ in range(draw(st.sampled_from([1, 1, 1, 2, 3]))):
        paths = list(_paths(cfg))
        op = draw(st.sampled_from(["delete", "unknown", "replace", "replace", "scale", "scale",
                                   "scale", "scale", "model", "empty"]))
        if op == "model":
            cfg["model"] = draw(st.one_of(st.sampled_from(sorted(LOADERS)), VALUES))
            continue
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = _parent(cfg, path)
        key = path[-1]
        value = parent[key]
        if op == "delete":
            del parent[key]
        elif op == "unknown":
            table = parent if isinstance(parent, dict) else cfg
            table[draw(st.one_of(st.text(min_size=1, max_size=8), st.integers()))] = \
                draw(VALUES)
        elif op == "empty":
            parent[key] = {}
        elif op == "scale" and _is_number(value):  # in range but physically odd
            parent[key] = value * draw(SCALES)
        elif op == "scale" and isinstance(value, list) and all(map(_is_number, value)):
            parent[key] = [v * draw(SCALES) for v in value]
        else:
            parent[key] = draw(VALUES)
    return cfg


@_settings(300)
@given(mutated_configs())
def test_mutated_configs_give_a_model_or_a_jaxdea_error(cfg):
    try:
        model = jaxdea.model_from_dict(cfg)
    except jaxdea.JaxdeaError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg, msg  # one line
        event(type(exc).__name__)
        return
    event(f"built {type(model).__name__}")
    assert model is not None


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_every_config_loads_unmutated(name):
    jaxdea.model_from_dict(copy.deepcopy(CONFIGS[name]))


# ---- calibration CSVs -----------------------------------------------------------------------

TIME_CSV = ["t [s]", "voltage [kV]", "displacement [mm]"], [
    ["0", "0", "0"], ["0.01", "1.5", "0.2"], ["0.02", "3", "0.4"], ["0.03", "1", "0.1"]], []
FREQ_CSV = ["f [Hz]", "amplitude [mm]", "P_out [mW]", "mass [g]", "damping [N s/m]"], [
    ["10", "0.5", "1", "2", "0.1"], ["20", "0.7", "2", "2", "0.1"],
    ["30", "0.4", "1.5", "2", "0.1"]], []
FREQ_META_CSV = ["f [Hz]", "amplitude [mm]", "P_out [mW]"], [
    ["10", "0.5", "1"], ["20", "0.7", "2"], ["30", "0.4", "1.5"]], [
    "# mass = 2 g", "# damping = 0.1 N s/m"]
ALL_UNITS = sorted({u for table in UNITS.values() for u in table})
CELLS = st.one_of(st.sampled_from(["", " ", "nan", "inf", "-1", "0", "1e400", "1,5", "1;5",
                                   '"1"', "x", "-0", "1e-9", "0x10", "1_0", "#", "\ufeff1",
                                   "-0.2", "5", "80", "1e3", "0.049", "0.051", "2.5"]),
                  st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.floats(-100, 100).map(repr),
                  st.text(max_size=5))
COMMENTS = st.sampled_from(["", "   ", "# a comment", "#", "# mass = 2 g",
                            "# damping = 0.1 N s/m", "# mass = x g", "# mass = 2",
                            "# damping = -1 N s/m", "# mass = nan kg", "sep=,", "sep=;"])


@st.composite
def mutated_csvs(draw):
    header, rows, meta = copy.deepcopy(draw(st.sampled_from([TIME_CSV, FREQ_CSV,
                                                             FREQ_META_CSV])))
    for _ in range(draw(st.sampled_from([0, 1, 1, 1, 2, 3]))):
        op = draw(st.sampled_from(["unit", "unit", "header", "cell", "cell", "cell", "cell",
                                   "missing", "extra", "dup", "drop", "meta"]))
        col = draw(st.integers(0, len(header) - 1))
        name = header[col].split("[")[0].strip()
        if op == "unit":
            valid = sorted(UNITS.get(name, {"m": 1}))
            unit = draw(st.one_of(st.sampled_from(valid), st.sampled_from(ALL_UNITS),
                                  st.text(max_size=4)))
            header[col] = f"{name} [{unit}]"
        elif op == "header":
            header[col] = draw(st.one_of(st.text(max_size=8),
                                         st.sampled_from([f"{n} [{next(iter(t))}]"
                                                          for n, t in UNITS.items()])))
        elif op in ("cell", "missing") and rows:
            row = rows[draw(st.integers(0, len(rows) - 1))]
            if col < len(row) and op == "cell":
                row[col] = draw(CELLS)
            elif col < len(row):
                del row[col]
        elif op == "extra":
            header.append(draw(st.sampled_from(["force [N]", "current [A]", "x", ""])))
            for row in rows:
                row.append(draw(CELLS))
        elif op == "dup":
            header.append(header[col])
            for row in rows:
                row.append(row[col] if col < len(row) else "1")
        elif op == "drop" and len(header) > 1:
            del header[col]
            for row in rows:
                if col < len(row):
                    del row[col]
        elif op == "meta":
            meta.append(draw(COMMENTS))
    delim = draw(st.sampled_from([","] * 8 + [";", "\t"]))
    lines = [*meta, delim.join(header)] + [delim.join(r) for r in rows]
    for _ in range(draw(st.sampled_from([0, 0, 1, 2, 3]))):  # blank and comment lines anywhere
        extra = draw(st.sampled_from(["", "   ", "# a comment", "#", "# mass ="]))
        lines.insert(draw(st.integers(0, len(lines))), extra)
    text = "\n".join(lines) + draw(st.sampled_from(["\n", "", "\r\n"]))
    if draw(st.booleans()):
        text = text.replace("\n", "\r\n")
    raw = (b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + text.encode("utf-8")
    if draw(st.integers(0, 19)) == 0:
        raw += b"\xff\xfe bad bytes"
    return raw


@_settings(1000)
@given(mutated_csvs())
def test_mutated_csvs_load_or_raise_a_data_error(raw):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "data.csv"
        path.write_bytes(raw)
        try:
            data = jaxdea.load_data(path)
        except jaxdea.DataError as exc:
            msg = str(exc)
            assert str(path) in msg and "\n" not in msg, msg
            event("DataError")
            return
    event(f"loaded {type(data).__name__}")
    for name, values in data.channels.items():
        assert np.all(np.isfinite(values)), name
    if isinstance(data, jaxdea.FrequencyResponse):
        assert np.all(data.f > 0) and np.all(data.mass >= 0) and np.all(data.damping >= 0)
        for name, values in data.channels.items():
            assert np.all(values >= 0), name


# ---- CLI ranges -----------------------------------------------------------------------------

NUMBER_TEXT = st.one_of(
    st.sampled_from(["0", "1", "-1", "1e308", "-1e308", "1e-308", "5e-324", "nan", "inf", "-inf",
                     "1e400", "", " ", "x", "1e20", "99999999999999999999", "0.1", "2", "10",
                     "1.0000000000000002", "1e-20", "1e-300", "1e300", "3.5", "1e9", "0x1"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**25, 10**25).map(str),
    st.integers(-3, 50).map(str),
    st.text(max_size=4),
)
SCALE_TEXT = st.sampled_from(["log", "lin", "LOG", "", "x"])


@st.composite
def range_texts(draw):
    n = draw(st.sampled_from([3, 3, 3, 3, 4, 4, 1, 2, 5]))
    parts = [draw(NUMBER_TEXT) for _ in range(n)]
    if n == 4 and draw(st.booleans()):
        parts[3] = draw(SCALE_TEXT)
    return ":".join(parts)


@st.composite
def numeric_range_texts(draw):
    """Mostly well-formed ranges whose numbers probe overflow, underflow and precision."""
    finite = st.floats(allow_nan=False, allow_infinity=False)
    lo = draw(st.one_of(finite, st.sampled_from([0.0, 1.0, 1e-300, 5e-324, 1e300, -1e308])))
    span = draw(st.one_of(st.floats(0, 1e308), st.sampled_from([0.0, 1.0, 1e-300, 1e-15])))
    with np.errstate(over="ignore"):
        hi = float(np.float64(lo) + span)
    third = draw(st.one_of(st.integers(1, 50).map(str), st.integers(1, 10**7).map(str),
                           st.floats(5e-324, 1e308).map(repr)))
    parts = [repr(lo), repr(hi), third]
    if draw(st.booleans()):
        parts.append(draw(st.sampled_from(["lin", "log"])))
    return ":".join(parts)


PARSERS = {
    "range": lambda text: parse_range(text, "--freq"),
    "points": lambda text: parse_points(text, "--mass"),
    "phases": lambda text: parse_phases(text, "--phase"),
    "lin_points": lambda text: lin_points(text, "--radius"),
}


#: Found by the test below before the fixes: OverflowError, MemoryError, a numpy "Maximum
#: allowed size exceeded", and silently wrong grids ([inf], [nan, inf, 1e308], ten zeros).
KNOWN_BAD = ["1e300:1e300:1", "-1e308:1e308:1e308", "1:2:1e-300", "1e-20:1e-19:1e-20",
             "-1e308:1e308:3:lin", "1:1.0000000000000002:5:lin", "1:2:99999999999999",
             "-1e308:0:3", "0:1e6:1e-6", "0:1.7976931330646228e+296:1.797693134862316e+296"]


def _with_known_bad(test):
    for text in KNOWN_BAD:
        test = example(text=text)(test)
    return test


@pytest.mark.parametrize("parser", sorted(PARSERS))
@_settings(1000)
@_with_known_bad
@given(text=st.one_of(numeric_range_texts(), range_texts(), st.text(max_size=12)))
def test_range_parsers_return_finite_arrays_or_raise_value_error(parser, text):
    try:
        out = PARSERS[parser](text)
    except ValueError as exc:
        assert "\n" not in str(exc)
        event("ValueError")
        return
    event("array")
    assert isinstance(out, np.ndarray) and out.ndim == 1 and out.size >= 1
    assert np.all(np.isfinite(out)), out
    assert np.all(np.diff(out) > 0), out  # distinct, increasing grid points


def test_range_values_are_unchanged_and_tiny_steps_stay_distinct():
    np.testing.assert_array_equal(parse_range("40:60:10"), [40.0, 50.0, 60.0])
    np.testing.assert_array_equal(parse_range("0.1:0.3:0.1"), [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(parse_range("1e300:1e300:1"), [1e300])
    tiny = parse_range("1e-20:1e-19:1e-20")
    np.testing.assert_allclose(tiny, 1e-20 * np.arange(1, 11))
    with pytest.raises(ValueError, match=r"more than 1000000 points"):
        parse_range("0:1e6:1e-6")
    with pytest.raises(ValueError, match=r"N = 99999999999999 is outside the allowed range"):
        parse_points("1:2:99999999999999", "--mass")
    with pytest.raises(ValueError, match=r"overflows a float64"):
        parse_points("-1e308:1e308:3:lin", "--mass")
    with pytest.raises(ValueError, match=r"equal at float64 precision"):
        lin_points("1:1.0000000000000002:5", "--radius")


@_settings(100)
@given(text=st.one_of(range_texts(), st.text(max_size=12)))
def test_sweep_with_a_bad_freq_exits_2_before_any_compute(tmp_path, text):
    try:
        parse_range(text)
    except ValueError:
        pass
    else:
        assume(False)  # a valid range would run a sweep
    err = io.StringIO()
    with mock.patch("jaxdea.load_config", side_effect=AssertionError("ran")), \
            mock.patch("jaxdea.sweep", side_effect=AssertionError("ran")), \
            contextlib.redirect_stderr(err):
        rc = main(["sweep", str(CONFIG_DIR / "scdea_ls.toml"), "--mass", "0.001",
                   "--damping", "0.1", f"--freq={text}", "--out", str(tmp_path / "s.nc")])
    assert rc == 2
    lines = err.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxdea: error: --freq"), lines
    assert not (tmp_path / "s.nc").exists()


SIM = ["simulate", str(CONFIG_DIR / "gu2017_final.toml")]
CAL = ["calibrate", str(CONFIG_DIR / "scdea_ls.toml"), "--fit", "dielectric.tau"]


@pytest.mark.parametrize("argv, message", [
    ([*SIM, "--signal", "sine", "--peak", "nan"], r"--peak must be a finite voltage, got nan"),
    ([*SIM, "--signal", "vp1", "--peak", "inf"], r"--peak must be a finite voltage, got inf"),
    ([*SIM, "--signal", "sine", "--period", "inf"], r"--period = inf s is outside the allowed"),
    ([*SIM, "--signal", "sine", "--rtol", "-1"], r"--rtol = -1.0 is outside the allowed range"),
    ([*SIM, "--signal", "sine", "--cycles", "100000000"],
     r"--cycles x --points = 40000000000 output samples is outside the allowed range"),
    ([*CAL, "--maxiter", "-1"], r"--maxiter = -1 is outside the allowed range \[1, inf\)"),
    ([*CAL, "--bounds", "dielectric.tau=1e-3:1e-2,dielectric.tau=1e-4:1"],
     r"--bounds gives dielectric.tau twice"),
])
def test_cli_option_mistakes_are_one_line_before_compute(tmp_path, argv, message):
    """Found by probing the commands: before, a traceback (MemoryError), an internal equinox
    message (--peak nan), or a run with a negative --rtol / --maxiter."""
    data = tmp_path / "fr.csv"
    data.write_text("# mass = 2 g\n# damping = 0.1 N s/m\nf [Hz],P_out [mW]\n60,1\n80,2\n")
    out = tmp_path / ("x.toml" if argv[0] == "calibrate" else "x.nc")
    extra = ["--data", str(data)] if argv[0] == "calibrate" else []
    err = io.StringIO()
    with mock.patch("jaxdea.studies.transient.transient", side_effect=AssertionError("ran")), \
            mock.patch("jaxdea.calibration.calibrate", side_effect=AssertionError("ran")), \
            contextlib.redirect_stderr(err):
        rc = main([*argv, *extra, "--out", str(out)])
    lines = err.getvalue().splitlines()
    assert rc == 2 and len(lines) == 1, lines
    assert re.search(message, lines[0]), lines[0]
    assert not out.exists()
