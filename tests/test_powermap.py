"""Power maps: equal to sweeps cell by cell, sharded over 4 devices, killed and resumed, and
bad arguments rejected before any compute.

Kept fast: 10 cycles (mean of the last 2) at >= 60 Hz, and one chunk shape (8 cells) for every
in-process run, so this file compiles the protocol once in-process (shared with the sweeps).
"""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import jaxdea
from jaxdea.cli import main
from jaxdea.cli.args import parse_points, parse_range
from jaxdea.engine.sharding import (
    MULTI_OUTPUT_FUSION,
    SMALL_WHILE_LOOP_OPTION,
    with_extra_option,
)
from jaxdea.studies.mapstore import open_map

# the module (jaxdea.powermap is the function)
pm = importlib.import_module("jaxdea.studies.powermap")

CONFIG = str(Path(__file__).parents[1] / "configs" / "scdea_ls.toml")
DOUBLE = str(Path(__file__).parents[1] / "configs" / "dcdea_ls.toml")
MASS, DAMPING, FREQ = [1e-3, 2e-3, 4e-3], [0.05, 0.1, 0.2], parse_range("60:200:20")
RUN = dict(cycles=10, average=2, chunk_cells=8, progress=False)
SRC = str(Path(__file__).parents[1] / "src")


def _env(**extra) -> dict:
    """A subprocess's environment: this checkout's jaxdea, ``extra`` (its own
    ``XLA_FLAGS``, say), and neither loop hoisting nor multi-output fusion, as in this
    process (``conftest.py``), so that a map the subprocess writes is this process's to the
    last bit (the CLI's ``powermap`` asks for multi-output fusion unless the user says
    ``=false``, which it then removes: XLA turns it on by its presence)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    flags = with_extra_option(env.get("XLA_FLAGS", ""), SMALL_WHILE_LOOP_OPTION, 0)
    env["XLA_FLAGS"] = with_extra_option(flags, MULTI_OUTPUT_FUSION, "false")
    return env


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


@pytest.fixture(scope="module")
def ref_map(model, tmp_path_factory):
    """The 3 x 3 x 8 map on one device, written to a NetCDF store."""
    store = tmp_path_factory.mktemp("ref") / "ref.nc"
    ds = jaxdea.powermap(model, mass=MASS, damping=DAMPING, freq=FREQ, store=store, **RUN)
    return ds, store


def test_map_equals_sweep_cell_by_cell(model, ref_map):
    ds, store = ref_map
    assert ds.P_out.dims == ("M", "c", "f") and ds.P_out.shape == (3, 3, 8)
    assert ds.M.attrs["units"] == "kg" and ds.c.attrs["units"] == "N s/m"
    assert ds.f.attrs["units"] == "Hz" and ds.P_max.attrs["units"] == "W"
    assert ds.attrs["chunks_computed"] == 9 and ds.attrs["chunks_reused"] == 0
    for i, m in enumerate(MASS):
        for j, c in enumerate(DAMPING):
            sw = jaxdea.sweep(model, mass=m, damping=c, freq=FREQ, cycles=10, average=2)
            cell = ds.isel(M=i, c=j)
            for k in ("P_out", "P_in", "amplitude"):
                np.testing.assert_allclose(cell[k].values, sw[k].values, rtol=1e-10, atol=0)
            np.testing.assert_array_equal(cell.status.values, sw.status.values)
    assert np.all(ds.status.values == 0)
    assert np.all(ds.P_out.values >= 0) and np.all(ds.P_in.values >= ds.P_out.values)
    assert np.all((ds.efficiency.values >= 0) & (ds.efficiency.values <= 1))
    # P_max over the steady cells (10 cycles leave some payloads none: NaN)
    p, any_steady = ds.P_out.where(ds.steady, -np.inf), ds.steady.any("f")
    np.testing.assert_array_equal(ds.P_max.values, p.max("f").where(any_steady).values)
    np.testing.assert_array_equal(ds.f_at_P_max.values,
                                  np.where(any_steady, FREQ[p.argmax("f").values], np.nan))
    # the store holds the same map (without the per-call chunk counts), and no parts are left
    on_disk = open_map(store)
    expect = ds.copy()
    for k in ("chunks_computed", "chunks_reused"):
        del expect.attrs[k]
    xr.testing.assert_identical(on_disk, expect)
    assert not Path(str(store) + ".parts").exists()


def test_p_max_skips_failed_cells():
    status = np.array([[0, 0, 1], [2, 3, 1]])
    p = np.array([[1.0, 2.0, 9.0], [5.0, 6.0, 7.0]])
    ds = xr.Dataset({"P_out": (("c", "f"), p), "status": (("c", "f"), status)},
                    coords={"c": [1.0, 2.0], "f": [10.0, 20.0, 30.0]})
    out = pm.reduce_over_f(ds)
    np.testing.assert_array_equal(out.P_max.values, [2.0, np.nan])
    np.testing.assert_array_equal(out.f_at_P_max.values, [20.0, np.nan])


def test_sharded_map_equals_single_device(ref_map, tmp_path):
    """4 CPU devices (each chunk split 2 cells per device) vs the single-device map."""
    _, ref_store = ref_map
    store = tmp_path / "sharded.zarr"
    script = textwrap.dedent(f"""
        import jax, jaxdea
        assert len(jax.devices()) == 4, jax.devices()
        model = jaxdea.load_config({CONFIG!r})
        ds = jaxdea.powermap(model, mass={MASS!r}, damping={DAMPING!r},
                             freq={FREQ.tolist()!r}, store={str(store)!r}, **{RUN!r})
        print("devices", len(jax.devices()), "chunks", ds.attrs["chunks_computed"])
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=4"),
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert "devices 4 chunks 9" in res.stdout
    a, b = open_map(ref_store), open_map(store)
    assert a.attrs == b.attrs
    for k in a.coords:
        np.testing.assert_array_equal(a[k].values, b[k].values)
    for k in ("status", "steps"):
        np.testing.assert_array_equal(a[k].values, b[k].values)
    # XLA compiles the 4-partition (SPMD) program with different fusions than the one-device
    # program, so results agree to rounding (measured <= ~1e-11 relative), not bit for bit.
    for k in ("P_out", "P_in", "P_in_signed", "efficiency", "amplitude", "v_rms", "P_max"):
        np.testing.assert_allclose(b[k].values, a[k].values, rtol=1e-10, atol=0, err_msg=k)


CLI_GRID = ["--mass", "1e-3:4e-3:4", "--damping", "0.05:0.2:4", "--freq", "60:200:2.5",
            "--cycles", "10", "--average", "2", "--chunk", "8"]


def test_cli_killed_then_resumed_matches_uninterrupted(model, tmp_path, capsys):
    # uninterrupted reference, in-process (same compiled 8-cell chunk as above)
    ref_store = tmp_path / "ref.zarr"
    axes = dict(mass=parse_points("1e-3:4e-3:4", "--mass"),
                damping=parse_points("0.05:0.2:4", "--damping"),
                freq=parse_range("60:200:2.5"))
    ref = jaxdea.powermap(model, **axes, store=ref_store, **RUN)
    n_chunks = ref.attrs["chunks_computed"]
    assert n_chunks == 4 * 4 * 57 // 8

    store = tmp_path / "map.zarr"
    parts = tmp_path / "map.zarr.parts"
    cmd = [sys.executable, "-m", "jaxdea.cli", "powermap", CONFIG, *CLI_GRID, "--out",
           str(store), "--no-progress"]
    # one CPU device, as the in-process reference (the CLI would use one per core, and a
    # sharded program rounds differently)
    env = _env(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax_cache"),
               XLA_FLAGS="--xla_force_host_platform_device_count=1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    t0 = time.time()
    try:
        while len(list(parts.glob("chunk_*.npz"))) < 3:
            assert proc.poll() is None, proc.communicate()
            assert time.time() - t0 < 240, "no chunk written"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    done = len(list(parts.glob("chunk_*.npz")))
    assert 3 <= done < n_chunks and (parts / "manifest.json").exists()
    assert not store.exists()

    # the interrupted run is protected: no --resume, or different settings, fail up front
    base = ["powermap", CONFIG, "--out", str(store), "--no-progress"]
    capsys.readouterr()
    assert main(base + CLI_GRID) == 2
    assert f"interrupted run of these settings ({done} of {n_chunks} chunks done): pass " \
           "--resume" in capsys.readouterr().err
    changed = [a if a != "10" else "12" for a in CLI_GRID]  # --cycles 12
    assert main(base + changed + ["--resume"]) == 2
    assert "cannot resume" in (err := capsys.readouterr().err) and "differ: cycles" in err

    res = subprocess.run(cmd + ["--resume"], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert f"chunks: {n_chunks - done} computed, {done} reused" in res.stdout
    assert not parts.exists()
    # the public reader opens the Zarr store without a warning (it is written without
    # consolidated metadata, on which a plain xarray.open_zarr warns)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        xr.testing.assert_identical(jaxdea.open_map(store), open_map(ref_store))


def test_resume_protection_messages(model, tmp_path, capsys):
    store = tmp_path / "m.nc"
    parts = pm.Parts(store, {"cycles": 10, "axes": [1.0]}, 3)
    parts.dir.mkdir()  # killed before the manifest was written: reused
    assert parts.open(resume=False) == set()
    assert parts.open(resume=False) == set()  # same run, nothing finished yet: reused
    parts.save(0, {"P_out": np.ones(8)})
    same = pm.Parts(store, {"cycles": 10, "axes": [1.0]}, 3)
    with pytest.raises(jaxdea.SweepError, match=r"interrupted run .*1 of 3 chunks.*--resume"):
        same.open(resume=False)
    assert same.open(resume=True) == {0}
    other = pm.Parts(store, {"cycles": 12, "axes": [1.0]}, 3)
    with pytest.raises(jaxdea.SweepError, match=r"different run \(settings that differ: cycles\)"):
        other.open(resume=True)
    with pytest.raises(jaxdea.SweepError, match=r"different run .*delete"):
        other.open(resume=False)


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        (dict(mass=[]), jaxdea.SweepError, "mass is empty"),
        (dict(damping=[-1.0, 0.1]), jaxdea.SweepError, "damping must be >= 0"),
        (dict(freq=[0.0, 60.0]), jaxdea.SweepError, "freq must be > 0"),
        (dict(freq=[60.0, np.nan]), jaxdea.SweepError, "freq must be finite"),
        (dict(mass=[2e-3, 1e-3]), jaxdea.SweepError, "mass must be strictly increasing"),
        (dict(phase=[0.0]), jaxdea.SweepError, "phase is only used with drive='both'"),
        (dict(drive="C"), jaxdea.SweepError, "drive = 'C' must be one of"),
        (dict(drive="both"), jaxdea.SweepError, "has one membrane"),
        (dict(protocol="magic"), jaxdea.SweepError, "protocol = 'magic' must be one of"),
        (dict(protocol="continuation", direction="up"), jaxdea.SweepError,
         "direction = 'up' must be one of forward, backward"),
        (dict(protocol="periodic", tol=0.0), jaxdea.SweepError,
         "tol = 0.0 is outside the allowed range (0, 1)"),
        (dict(store="m.h5"), jaxdea.SweepError, "store must end in .zarr"),
        (dict(chunk_cells=0), jaxdea.SweepError, "chunk_cells must be an integer >= 1"),
        (dict(cycles=5, average=6), jaxdea.SweepError, "average = 6 must be <= cycles = 5"),
        (dict(resume=True), jaxdea.SweepError, "resume=True needs a store"),
        (dict(control=jaxdea.StepControl(rtol=0.0)), jaxdea.SweepError, "rtol = 0.0"),
        (dict(control=jaxdea.StepControl(precision="half")), jaxdea.SweepError,
         "precision = 'half' must be one of 'double', 'single'"),
        (dict(control=jaxdea.StepControl(solver="rk45")), jaxdea.SweepError,
         "solver = 'rk45' must be one of lawson, exponential"),
        (dict(control=jaxdea.StepControl(precision="single")), jaxdea.SweepError,
         "early_exit = 1e-08 is below the periodicity float32 lanes resolve"),
        (dict(control=jaxdea.StepControl(precision="single"), protocol="periodic"),
         jaxdea.SweepError, "protocol='periodic' needs 'double'"),
        (dict(control=jaxdea.StepControl(rtol=1e-7, precision="single"), early_exit=None),
         jaxdea.SweepError, "rtol = 1e-07 is below what single precision resolves"),
        (dict(mass=np.geomspace(1e-4, 1e-2, 100_000), damping=np.geomspace(0.1, 10, 100_000)),
         jaxdea.SweepError, "GiB of memory"),
    ],
)
def test_bad_arguments_fail_before_compute(model, monkeypatch, kwargs, error, message):
    monkeypatch.setattr(pm, "_run_chunk", lambda *a, **k: pytest.fail("computed"))
    args = dict(mass=MASS, damping=DAMPING, freq=FREQ, progress=False) | kwargs
    with pytest.raises(error, match=message.replace("(", r"\(").replace(")", r"\)")):
        jaxdea.powermap(model, **args)


def test_bad_phase_on_double_cone(monkeypatch):
    monkeypatch.setattr(pm, "_run_chunk", lambda *a, **k: pytest.fail("computed"))
    dc = jaxdea.load_config(DOUBLE)
    with pytest.raises(jaxdea.SweepError, match=r"phase = 7.0 rad is outside .*\[0, 2 pi\)"):
        jaxdea.powermap(dc, mass=MASS, damping=DAMPING, freq=FREQ, phase=[0.0, 7.0],
                        drive="both")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--mass", "4e-3:1e-3:3"], "--mass is inverted"),
        (["--mass", "0:1e-3:3"], "--mass with log spacing needs MIN > 0"),
        (["--damping", "0.1:1:0"], "--damping is empty"),
        (["--damping", "0.1:1:3:cubic"], "--damping spacing must be log or lin"),
        (["--freq", "200:60:1"], "--freq is empty"),
        (["--phase", "0:6.2832:4"], "phase is only used with drive='both'"),
        (["--protocol", "periodic", "--tol", "2"], "tol = 2.0 is outside the allowed range"),
        (["--out", "m.h5"], "store must end in .zarr"),
        (["--chunk", "0"], "chunk_cells must be an integer >= 1"),
    ],
)
def test_cli_bad_arguments(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.setattr(pm, "_run_chunk", lambda *a, **k: pytest.fail("computed"))
    base = {"--mass": "1e-3:4e-3:3", "--damping": "0.05:0.2:3", "--freq": "60:200:20",
            "--out": str(tmp_path / "m.zarr")}
    argv = ["powermap", CONFIG, "--no-progress"]
    for k, v in base.items():
        if k not in args:
            argv += [k, v]
    assert main(argv + args) == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_parse_points_and_phases():
    np.testing.assert_allclose(parse_points("1e-4:1e-2:3", "--mass"), [1e-4, 1e-3, 1e-2])
    np.testing.assert_allclose(parse_points("0:1:3:lin", "--mass"), [0.0, 0.5, 1.0])
    from jaxdea.cli.args import parse_phases
    ph = parse_phases("0:6.2832:8")
    assert ph.size == 8 and ph[0] == 0.0 and ph[-1] < 2 * np.pi


def test_plots(ref_map, tmp_path, capsys):
    _, store = ref_map
    for kind, extra in (("pmax", []), ("pout-f-c", ["--mass", "2e-3"]),
                        ("ratio", ["--other", str(store)])):
        png = tmp_path / f"{kind}.png"
        assert main(["plot", str(store), "--kind", kind, *extra, "--out", str(png)]) == 0
        assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 10_000
    assert main(["plot", str(store), "--kind", "ratio", "--out", str(tmp_path / "x.png")]) == 2
    assert "--kind ratio needs --other" in capsys.readouterr().err
