"""The continuation and periodic protocols against the papers' protocol they build on.

- continuation: each frequency really starts from the previous one's final state (equal to
  an explicit hand-over through ``run_protocol(initial=...)``), both directions, on maps and
  on 4 devices;
- periodic: agrees with a 400-cycle paper run where that run has converged, including a
  lightly damped resonance the 100-cycle paper run has not finished, and needs shooting to
  get there (without Newton the same cells are reported as not converged, status 4).

SCDEA-LS at >= 60 Hz keeps the compiles and runs short.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxdea
from jaxdea.engine.batch import chain_heads, chain_successors, run_cells
from jaxdea.engine.periodic import flatten_dynamical, periodic_cells, with_dynamical
from jaxdea.studies.loadings import make_loadings

CONFIG = str(Path(__file__).parents[1] / "configs" / "scdea_ls.toml")
SRC = str(Path(__file__).parents[1] / "src")
FREQ = np.array([60.0, 80.0, 100.0])
SHORT = dict(cycles=6, average=2)


def _run(model, loads, **kw):
    """The papers' protocol through the compiled engine the sweeps use (shared compile)."""
    return run_cells(model, loads, **kw)


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


def test_chain_successors_layout():
    np.testing.assert_array_equal(chain_successors(3), [1, 2, 3])
    np.testing.assert_array_equal(chain_successors(3, direction="backward"), [3, 0, 1])
    # (blocks, f, rest) = (2, 2, 2): cell (b, j, r) -> (b, j + 1, r)
    np.testing.assert_array_equal(chain_successors(2, 2, "forward", 2),
                                  [2, 3, 8, 8, 6, 7, 8, 8])
    # chains (one lane each): one per (block, rest); independent cells are chains of one
    assert chain_heads(chain_successors(3)) == 1
    assert chain_heads(chain_successors(2, 2, "backward", 2)) == 4
    assert chain_heads(np.full(5, 5)) == 5


def test_continuation_hands_over_the_final_state(model):
    """Short runs (6 cycles, not yet periodic), so the start state shows in the result."""
    fwd = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=FREQ, protocol="continuation",
                       **SHORT)
    bwd = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=FREQ, protocol="continuation",
                       direction="backward", **SHORT)
    paper = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=FREQ, **SHORT)
    assert np.all(fwd.status.values == 0) and np.all(bwd.status.values == 0)
    # chain heads start from rest: equal to the paper protocol (to rounding: a continuation
    # sweep runs its one chain on one lane, the paper sweep on several)
    np.testing.assert_allclose(fwd.P_out.values[0], paper.P_out.values[0], rtol=1e-12)
    np.testing.assert_allclose(bwd.P_out.values[-1], paper.P_out.values[-1], rtol=1e-12)
    # the others do not ...
    assert abs(fwd.P_out.values[1] / paper.P_out.values[1] - 1) > 1e-3
    assert abs(bwd.P_out.values[1] / paper.P_out.values[1] - 1) > 1e-3
    # ... and equal an explicit hand-over of the previous cell's final state
    loads = make_loadings(model, 2e-3, 0.1, FREQ)
    first = _run(model, loads, **SHORT)
    start = jax.tree_util.tree_map(lambda a: a[np.array([0, 0, 1])], first.final_state)
    second = _run(model, loads, initial=start, **SHORT)
    np.testing.assert_allclose(fwd.P_out.values[1], second.P_out[1], rtol=1e-12)
    np.testing.assert_allclose(fwd.amplitude.values[1], second.amplitude[1], rtol=1e-12)


def test_continuation_map_equals_sweeps_and_four_devices(model, tmp_path):
    mass, damping = [1e-3, 2e-3], [0.1, 0.2]
    run = dict(protocol="continuation", progress=False, **SHORT)
    ds = jaxdea.powermap(model, mass=mass, damping=damping, freq=FREQ, chunk_cells=3, **run)
    for i, m in enumerate(mass):
        for j, c in enumerate(damping):
            sw = jaxdea.sweep(model, mass=m, damping=c, freq=FREQ, protocol="continuation",
                              **SHORT)
            np.testing.assert_allclose(ds.P_out.values[i, j], sw.P_out.values, rtol=1e-12)
    store = tmp_path / "cont.nc"
    script = textwrap.dedent(f"""
        import jax, jaxdea
        assert len(jax.devices()) == 4
        model = jaxdea.load_config({CONFIG!r})
        ds = jaxdea.powermap(model, mass={mass!r}, damping={damping!r},
                             freq={FREQ.tolist()!r}, store={str(store)!r}, **{run!r})
        print("chunks", ds.attrs["chunks_computed"])
    """)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(PYTHONPATH=SRC + os.pathsep + env.get("PYTHONPATH", ""),
               XLA_FLAGS="--xla_force_host_platform_device_count=4")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "chunks 1" in res.stdout  # 4 chains of 3 f: one chunk, one chain per device
    sharded = jaxdea.studies.mapstore.open_map(store)
    np.testing.assert_array_equal(sharded.status.values, ds.status.values)
    np.testing.assert_allclose(sharded.P_out.values, ds.P_out.values, rtol=1e-10)


@pytest.fixture(scope="module")
def long_runs(model):
    """A lightly damped payload (M = 10 g, c = 0.1 N s/m: ~0.2 s decay) at three frequencies,
    one near the resonance: the periodic protocol vs 100- and 400-cycle paper runs."""
    freq = np.array([60.0, 85.0, 140.0])
    loads = make_loadings(model, 1e-2, 0.1, freq)
    # strict runs (no early exit): the references are >= 400 and 100 full cycles
    paper400 = _run(model, loads, cycles=400, average=5, early_exit=None)
    paper100 = _run(model, loads, cycles=100, average=5, early_exit=None)
    periodic = periodic_cells(model.actuator, loads)
    return freq, loads, paper100, paper400, periodic


def test_periodic_agrees_with_long_paper_run(long_runs):
    freq, _, paper100, paper400, periodic = long_runs
    assert np.all(np.asarray(periodic.status) == 0)
    converged = np.asarray(paper400.residual) < 1e-8
    assert converged.all(), paper400.residual
    err = np.abs(np.asarray(periodic.P_out) / np.asarray(paper400.P_out) - 1)
    assert err.max() < 2e-3 * 0.1, err  # 10x inside the 0.2 %
    np.testing.assert_allclose(periodic.amplitude, paper400.amplitude, rtol=1e-3)
    np.testing.assert_allclose(periodic.P_in, paper400.P_in, rtol=1e-3)
    assert np.all(np.asarray(periodic.residual) < 1e-6)
    # the 100-cycle run is still visibly off at the slowest cell (why 'periodic' exists)
    assert np.max(np.asarray(paper100.residual)) > 1e-5
    # and periodic got there in far fewer cycles than the paper's 100
    assert np.all(np.asarray(periodic.cycles_run) < 40), periodic.cycles_run


def test_periodic_needs_newton_where_settling_is_slow(model, long_runs):
    _, loads, _, _, periodic = long_runs
    settle_only = periodic_cells(model.actuator, loads, newton=0)
    status = np.asarray(settle_only.status)
    assert np.any(status == 4), "expected a cell that 12 cycles from rest do not settle"
    assert np.all(np.asarray(periodic.status)[status == 4] == 0)


def test_flatten_roundtrip(model):
    y = model.actuator.initial_state()
    flat = flatten_dynamical(y)
    assert flat.shape == (5,)
    back = with_dynamical(y, flat + 1.0)
    np.testing.assert_allclose(back.q, y.q + 1.0)
    np.testing.assert_allclose(back.xi_el, y.xi_el + 1.0)
    np.testing.assert_array_equal(back.energy_in, y.energy_in)


def test_periodic_rejects_bad_settings(model):
    loads = make_loadings(model, 1e-3, 0.1, FREQ)
    with pytest.raises(ValueError, match="tol = 0 is outside the allowed range"):
        periodic_cells(model.actuator, loads, tol=0)
    with pytest.raises(ValueError, match="warmup must be an integer >= 2"):
        periodic_cells(model.actuator, loads, warmup=1)
    with pytest.raises(jaxdea.SweepError, match="protocol = 'steady' must be one of"):
        jaxdea.sweep(model, mass=1e-3, damping=0.1, freq=FREQ, protocol="steady")


def test_paper_early_exit_equals_the_full_run(model):
    """The papers' protocol stops a cell once its trajectory is periodic to EARLY_EXIT (the
    remaining cycles would repeat it): the metrics equal the full 100-cycle run's to ~1e-7.
    A lightly damped resonance that has not converged by cycle 100 runs every cycle and is
    unchanged (same last-5 window)."""
    freq = np.array([5.0, 30.0, 85.0])
    loads = make_loadings(model, np.array([1e-3, 1e-3, 1e-2]), np.array([1.0, 1.0, 0.1]), freq)
    full = _run(model, loads, early_exit=None)
    early = _run(model, loads)
    cycles = np.asarray(early.cycles_run)
    assert np.all(np.asarray(full.cycles_run) == 100) and np.all(np.asarray(early.status) == 0)
    assert cycles[0] < 20 and cycles[1] < 60 and cycles[2] == 100, cycles
    assert np.asarray(early.steps)[0] < 0.2 * np.asarray(full.steps)[0]
    for k in ("P_out", "P_in", "P_in_signed", "amplitude", "v_rms", "efficiency"):
        a, b = np.asarray(getattr(early, k)), np.asarray(getattr(full, k))
        np.testing.assert_allclose(a[:2], b[:2], rtol=1e-6, err_msg=k)
        np.testing.assert_allclose(a[2], b[2], rtol=1e-13, err_msg=k)
    with pytest.raises(jaxdea.SweepError, match="early_exit = 0 must be None"):
        jaxdea.sweep(model, mass=1e-3, damping=0.1, freq=FREQ, early_exit=0)


def test_stage_order_gives_every_device_an_equal_share_of_every_block():
    """A warm-started chain's stage deals each block (mass) evenly over the devices, lowest
    frequency first on each: the first stage runs one block at a time, and plain round-robin
    over all columns would give all of a block to one device (two devices, even blocks)."""
    from jaxdea.engine.warmstart import stage_order

    freq = np.tile([30.0, 10.0, 50.0, 20.0, 40.0], 4)  # 4 blocks of 5 columns
    block = np.repeat(np.arange(4), 5)
    order = stage_order(freq, block, 2)
    assert order.size == 2 * 4 * 3 and set(order) == set(range(20))  # each block padded
    for slice_ in order.reshape(2, -1):
        assert (np.diff(freq[slice_]) >= 0).all()
        assert (np.bincount(block[slice_], minlength=4) == 3).all()
    assert (np.sort(stage_order(freq[:5], block[:5], 1)) == np.arange(5)).all()


def test_predictor_extrapolates_polynomials_exactly_and_drops_missing_orbits():
    """The warm start's predictor continues a polynomial of degree k - 1 through the last k
    stages exactly, uses fewer stages where older orbits are missing, and its history keeps
    only orbits of consecutive converged stages."""
    from jaxdea.engine.warmstart import predict, remember

    def orbit(j):  # (3 cells, d = 2): cubic in the stage index
        return np.array([[j ** 3 - 2 * j, 1.0 + j], [0.5 * j ** 2, -j], [j, 2.0]])

    history = np.stack([orbit(j) for j in (4, 3, 2, 1)])  # newest first
    np.testing.assert_allclose(predict(history), orbit(5), rtol=1e-12)
    history[2:, 0] = np.nan  # cell 0: only two stages -> the secant
    np.testing.assert_allclose(predict(history)[0], 2 * orbit(4)[0] - orbit(3)[0])
    history[1:, 1] = np.nan  # cell 1: one stage -> its orbit
    np.testing.assert_allclose(predict(history)[1], orbit(4)[1])
    np.testing.assert_allclose(predict(history)[2], orbit(5)[2], rtol=1e-12)
    new = remember(history, orbit(5), ok=np.array([True, True, False]),
                   recent=np.array([True, False, True]))
    np.testing.assert_allclose(new[:2, 0], [orbit(5)[0], orbit(4)[0]])  # consecutive
    assert np.isnan(new[1:, 1]).all() and (new[0, 1] == orbit(5)[1]).all()  # not
    assert (new[0, 2] == orbit(4)[2]).all() and np.isnan(new[1:, 2]).all()  # failed: seed


def test_chord_columns_repeat_the_stage_by_stage_chain_iteration_for_iteration(model):
    """The warm-started chain's later stages, every column at its own pace
    (``chord_columns``), do for every cell exactly what the stage-by-stage chain does
    (``chord_cells`` on a whole stage at a time, then ``predict``/``remember``): the same
    periods, steps and status, and the same powers within the Newton tolerance (a cell's
    lane may differ, and so may its rounding). Three columns (two of them alike, as padding
    makes them) of six stages."""
    from jaxdea.engine.batch import take_cells
    from jaxdea.engine.chord import chord_cells
    from jaxdea.engine.periodic import flatten_dynamical, periodic_cells, with_dynamical
    from jaxdea.engine.warmstart import PREDICTOR_POINTS, chord_columns, predict, remember
    from jaxdea.studies.loadings import make_loadings

    damping, freq = np.logspace(-1, 1, 6), np.array([60.0, 160.0, 60.0])
    loadings = make_loadings(model, 2e-3, damping[:, None], freq[None, :])
    slots = np.arange(damping.size * freq.size).reshape(damping.size, -1).T  # (column, stage)
    kw = dict(lanes=3, tol=1e-6)
    first = take_cells(loadings, slots[:, -1])
    res, jac = periodic_cells(model.actuator, first, with_jacobian=True, active=np.ones(3, bool),
                              **kw)
    ok = np.asarray(res.status) == 0
    flat = np.asarray(flatten_dynamical(res.final_state))
    seed = res.final_state

    def start():
        return (remember(np.full((PREDICTOR_POINTS,) + flat.shape, np.nan), flat, ok,
                         np.zeros_like(ok)), np.where(ok[:, None, None], jac, np.nan))

    history, j = start()  # the reference: one stage at a time
    recent, expect = ok, {}
    for stage in range(damping.size - 2, -1, -1):
        r, new_j, conv, orbit = chord_cells(model.actuator,
                                            take_cells(loadings, slots[:, stage]),
                                            with_dynamical(seed, predict(history)), j, **kw)
        j = np.where(conv[:, None, None], new_j, j)
        history = remember(history, orbit, conv, recent)
        recent = conv
        for col in range(3):
            expect[slots[col, stage]] = (int(r.cycles_run[col]), int(r.steps[col]),
                                         int(r.status[col]), float(r.P_out[col]))
    history, j = start()
    got = {}
    for where, cells, r, conv, _ in chord_columns(model.actuator, loadings, slots, seed,
                                                  history, j, ok, **kw):
        for i, cell in enumerate(cells):
            got[int(cell)] = (int(r.cycles_run[i]), int(r.steps[i]), int(r.status[i]),
                              float(r.P_out[i]))
    assert sorted(got) == sorted(expect)
    for cell, ref in expect.items():
        assert got[cell][:3] == ref[:3], (cell, got[cell], ref)
        # a cell may sit in another lane, and rounding moves the converged orbit within the
        # Newton tolerance (1e-6 on the state; 1.3e-7 on P_out seen on a 6250-cell map)
        np.testing.assert_allclose(got[cell][3], ref[3], rtol=1e-6)
    assert all(v[2] == 0 for v in got.values())
    periods = np.mean([v[0] for v in got.values()])  # 4.9 on this coarse grid
    assert 1 <= periods < 6, periods


def test_neighbour_warm_starts_equal_the_from_rest_map(model):
    """``start="neighbour"`` (issue 16): each cell continued by chord iterations from its
    neighbouring damping's orbit gives the from-rest periodic map's numbers (tolerance 1e-6
    on the state: ~1e-4 on the powers) in fewer periods per cell, for every cell after the
    chain's first stage (the heaviest damping: solved from rest for the first mass, and
    continued from the mass before for the others); a cell below ``REST_BELOW`` is solved
    from rest exactly as ``start="rest"`` solves it."""
    from jaxdea.engine.warmstart import REST_BELOW

    kw = dict(mass=[2e-3, 2.5e-3, 3e-3], damping=np.logspace(-1, 1, 5),
              freq=[REST_BELOW / 2, 60.0, 110.0, 160.0], protocol="periodic", progress=False)
    warm = jaxdea.powermap(model, start="neighbour", **kw)
    cold = jaxdea.powermap(model, **kw)
    assert warm.attrs["start"] == "neighbour" and cold.attrs["start"] == "rest"
    assert (warm.status == 0).all() and (cold.status == 0).all()
    for name in ("P_out", "P_in"):
        err = float((abs(warm[name] - cold[name]) / cold[name]).max())
        assert err < 2e-4, (name, err)
    chained = dict(c=slice(0, -1), f=slice(1, None))  # not the head stage, not < REST_BELOW
    fewer = warm.cycles_run.isel(chained) < cold.cycles_run.isel(chained)
    assert fewer.mean() > 0.8, warm.cycles_run.values
    head = dict(c=-1, f=slice(1, None))  # the first stage: from rest for the first mass only
    first, later = dict(head, M=0), dict(head, M=slice(1, None))
    assert (warm.cycles_run.isel(first) == cold.cycles_run.isel(first)).all()
    assert (warm.cycles_run.isel(later) < cold.cycles_run.isel(later)).all(), \
        warm.cycles_run.values
    low = dict(f=0)  # from rest in both: the same solve, the same numbers
    np.testing.assert_allclose(warm.P_out.isel(low), cold.P_out.isel(low), rtol=1e-12)
    # one branch here: no cell has a second orbit, and only a warm-started map says so
    assert warm.coexist.dtype == bool and not warm.coexist.any()
    assert "coexist" not in cold and "another stable" in warm.coexist.attrs["long_name"]
    # a protocol object says the same, and the setting is checked before any compute
    assert jaxdea.Periodic(start="neighbour").start == "neighbour"
    with pytest.raises(jaxdea.SweepError, match="needs protocol='periodic'"):
        jaxdea.powermap(model, **{**kw, "protocol": "paper", "start": "neighbour"})
    with pytest.raises(jaxdea.SweepError, match="start = 'up' must be one of rest, neighbour"):
        jaxdea.Periodic(start="up")
    with pytest.raises(jaxdea.SweepError, match="a sweep \\(one payload\\) has none"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0],
                     protocol=jaxdea.Periodic(start="neighbour"))



def test_forward_and_backward_sweeps_find_the_two_orbits_of_a_hardening_resonance(model):
    """Continuation exposes jumps (README): with the membrane's viscous branches relaxing at
    once (tau 1e-5 s: no viscous damping) and a light payload damping, SCDEA-LS's resonance
    hardens and two steady orbits coexist at 84 Hz. The forward sweep rides the upper branch
    past the fold (152 mW), the backward sweep stays on the lower one (16.1 mW), and the
    periodic protocol from rest, an independent route, lands on the lower one too. Both
    sweeps are steady there: two orbits, not an unsettled transient."""
    import equinox as eqx

    light = eqx.tree_at(lambda m: (m.actuator.membrane.dielectric.tau,
                                   m.actuator.membrane.electrode.tau), model, (1e-5, 1e-5))
    kw = dict(mass=2e-3, damping=0.01, cycles=800)
    up = jaxdea.sweep(light, **kw, freq=[78.0, 80.0, 82.0, 84.0], protocol="continuation")
    down = jaxdea.sweep(light, **kw, freq=[84.0, 86.0, 88.0], protocol="continuation",
                        direction="backward")
    rest = jaxdea.sweep(light, mass=2e-3, damping=0.01, freq=[84.0], protocol="periodic")
    high, low = float(up.P_out.sel(f=84.0)), float(down.P_out.sel(f=84.0))
    assert bool(up.steady.sel(f=84.0)) and bool(down.steady.sel(f=84.0))
    assert high > 5 * low, (high, low)  # 152.0 mW against 16.09 mW
    assert int(rest.status[0]) == 0
    np.testing.assert_allclose(float(rest.P_out[0]), low, rtol=1e-3)


def test_frequency_rows_of_a_block():
    """The rows of the continuation along f (``coexist.frequency_rows``): a row per mass,
    damping and phase, in ascending f whatever the grid's order; none where the grid is not
    one monotonic axis."""
    from jaxdea.engine.coexist import frequency_rows

    # (blocks, n_chain, f x phase) = (1, 2, 3 x 2), f given descending
    freq = np.tile(np.repeat([30.0, 20.0, 10.0], 2), 2)
    rows = frequency_rows(freq, (1, 2, 6))
    np.testing.assert_array_equal(rows, [[4, 2, 0], [5, 3, 1], [10, 8, 6], [11, 9, 7]])
    assert (np.diff(freq[rows], axis=1) > 0).all()
    assert frequency_rows(np.array([10.0, 30.0, 20.0, 10.0]), (1, 1, 4)) is None


def test_a_warm_started_map_flags_the_upper_branch_of_a_hardening_resonance(model):
    """``coexisting``'s continuation along f (issue 16) on the resonance of the test above:
    a warm-started map over 78-88 Hz reports the lower orbit at 84 Hz (as the backward
    sweep and the from-rest orbit are), and flags it and 85 Hz, where the orbit continued
    up f from below the resonance rides the upper branch; below the resonance and past the
    upper branch's fold (86 Hz: one orbit, the forward sweep drops back) nothing is
    flagged. The chain along c and the mass check alone flag nothing here."""
    import equinox as eqx

    light = eqx.tree_at(lambda m: (m.actuator.membrane.dielectric.tau,
                                   m.actuator.membrane.electrode.tau), model, (1e-5, 1e-5))
    freq = np.arange(78.0, 89.0)
    got = jaxdea.powermap(light, mass=[2e-3], damping=[0.01, 0.0125], freq=freq,
                          protocol="periodic", start="neighbour", progress=False)
    row = got.sel(M=2e-3, c=0.01)
    flagged = freq[row.coexist.values]
    assert {84.0, 85.0} <= set(flagged) <= {82.0, 83.0, 84.0, 85.0}, flagged
    assert int(row.status.sel(f=84.0)) == 0
    np.testing.assert_allclose(float(row.P_out.sel(f=84.0)), 16.09e-3, rtol=2e-3)
    assert not got.coexist.sel(f=slice(None, 81.0)).any()
    assert not got.coexist.sel(f=slice(86.0, None)).any()


def test_a_warm_started_map_resumes_with_its_coexistence_flags(model, tmp_path, monkeypatch):
    """A ``start="neighbour"`` map's per-cell ``coexist`` flag is part of each chunk's saved
    part: a run interrupted after its first chunk resumes with that chunk's flags as saved
    (here set by a stand-in for ``coexisting`` on the first cell of each chunk) and computes
    the rest; the powers equal an uninterrupted run's."""
    from jaxdea.engine.warmstart import REST_BELOW
    from jaxdea.studies import distributed
    from jaxdea.studies import powermap as pm

    # the grid of test_neighbour_warm_starts_equal_the_from_rest_map, a mass per chunk
    kw = dict(mass=[2e-3, 2.5e-3, 3e-3], damping=np.logspace(-1, 1, 5),
              freq=[REST_BELOW / 2, 60.0, 110.0, 160.0], protocol="periodic",
              start="neighbour", chunk_cells=20, progress=False)
    ref = jaxdea.powermap(model, **kw)
    assert ref.attrs["chunks_computed"] == 3 and not ref.coexist.any()
    store = tmp_path / "map.zarr"
    real_coexisting, real_run = distributed.coexisting, pm._run_chunk
    calls = []

    def mark_first(actuator, loadings, shape, results, **k):
        flag, iterated = real_coexisting(actuator, loadings, shape, results, **k)
        flag[0] = True
        return flag, iterated

    def stop_second(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_run(*a, **k)

    monkeypatch.setattr(distributed, "coexisting", mark_first)
    monkeypatch.setattr(pm, "_run_chunk", stop_second)
    with pytest.raises(KeyboardInterrupt):
        jaxdea.powermap(model, **kw, store=store)
    assert len(list((tmp_path / "map.zarr.parts").glob("chunk_*.npz"))) == 1
    monkeypatch.undo()
    got = jaxdea.powermap(model, **kw, store=store, resume=True)
    assert (got.attrs["chunks_computed"], got.attrs["chunks_reused"]) == (2, 1)
    assert got.coexist.values[0, 0, 0] and got.coexist.sum() == 1  # chunk 0's mark
    assert jaxdea.open_map(store).coexist.sum() == 1
    for name in ("P_out", "P_in", "status"):
        np.testing.assert_allclose(got[name], ref[name], rtol=1e-12, err_msg=name)


def test_a_cell_off_its_neighbours_branch_is_flagged(model):
    """``coexisting`` (issue 16): a cell whose orbit is not the one its mass neighbours'
    orbits continue to is iterated from its neighbour's orbit, converges to another stable
    orbit and is flagged, with that work added to its steps; its neighbours, iterated from
    the odd orbit, converge back to their own and are not flagged. On the map's true orbits
    (one branch, as the from-rest map confirms above) nothing is flagged. The odd orbit is
    another frequency's (a stable orbit of this model, on no branch of this cell's)."""
    import equinox as eqx

    from jaxdea.engine.coexist import coexisting
    from jaxdea.engine.sharding import to_host
    from jaxdea.engine.warmstart import neighbour_chain

    mass, damping, freq = np.array([2e-3, 2.5e-3, 3e-3, 3.5e-3]), np.logspace(-1, 1, 4), \
        np.array([60.0, 110.0, 160.0])
    shape = (mass.size, damping.size, freq.size)
    loadings = make_loadings(model, mass[:, None, None], damping[None, :, None], freq)
    res, jac = neighbour_chain(model.actuator, loadings, shape, with_jacobian=True)
    res = to_host(res)
    assert (np.asarray(res.status) == 0).all()
    # the Jacobians the chain converged with, handed over for the check's chord iterations
    assert jac.shape == (res.status.size,) + (flatten_dynamical(res.final_state).shape[1],) * 2
    assert np.isfinite(jac).all(axis=(1, 2)).mean() > 0.9
    kw = dict(jacobian=jac)
    flag, _ = coexisting(model.actuator, loadings, shape, res, **kw)
    assert not flag.any()
    # the mass check alone, screened finer than its default (a planted orbit is nearer to
    # the cell's own than a real branch is: 1.4-1.9 there, against SCREEN 0.7)
    kw.update(screen_f=np.inf, screen=3e-2)
    flag, iterated = coexisting(model.actuator, loadings, shape, res, **kw)
    assert not flag.any() and iterated.sum() <= 6, iterated.sum()  # few pass the screen

    odd, other = (np.ravel_multi_index(i, shape) for i in ((2, 1, 1), (2, 1, 2)))
    flat = np.asarray(flatten_dynamical(res.final_state))
    flat[odd] = flat[other]
    res = eqx.tree_at(lambda r: r.final_state, res, with_dynamical(res.final_state, flat))
    steps = np.asarray(res.steps).copy()
    flag, iterated = coexisting(model.actuator, loadings, shape, res, **kw)
    assert np.nonzero(flag)[0].tolist() == [odd]
    after = np.ravel_multi_index((3, 1, 1), shape)  # its partner is the odd cell
    assert iterated[[odd, after]].all()
    assert (np.asarray(res.steps)[iterated] > steps[iterated]).all()
    assert (np.asarray(res.steps)[~iterated] == steps[~iterated]).all()


def test_a_chord_period_runs_in_the_settling_program(model):
    """A chord iteration's period (``periodic.one_period``) is the settling program with a
    budget of one period: after a from-rest ``periodic_cells`` on the same cells it compiles
    nothing, and it gives what one strict period of the papers' protocol gives from the same
    states (the metrics of that period, its final state, status 0)."""
    import equinox as eqx

    from jaxdea.engine.lanes import run_protocol
    from jaxdea.engine.periodic import one_period, settle_pools, settle_program
    from jaxdea.engine.sharding import to_host

    loads = make_loadings(model, 1e-2, 0.1, FREQ)
    settled = to_host(periodic_cells(model.actuator, loads, lanes=3))
    start = settled.final_state
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **_: compiles.append(name) if name.startswith("/jax/core/compile")
        else None)
    first = len(compiles)
    got = one_period(settle_program(tuple(jax.devices()[:1])), model.actuator, loads, start,
                     np.array([True, False, True]), control=jaxdea.StepControl(),
                     pools=settle_pools(3, 3), driven=None)
    assert compiles[first:] == []  # the program periodic_cells compiled
    ref = to_host(eqx.filter_jit(run_protocol)(model.actuator, loads, cycles=1, average=1,
                                               initial=start, pools=(3,)))
    np.testing.assert_array_equal(got.status, [0, 0, 0])
    for k in ("P_out", "P_in", "amplitude", "steps"):
        np.testing.assert_allclose(getattr(got, k)[[0, 2]], getattr(ref, k)[[0, 2]],
                                   rtol=1e-12, err_msg=k)
    np.testing.assert_allclose(flatten_dynamical(got.final_state)[[0, 2]],
                               flatten_dynamical(ref.final_state)[[0, 2]], rtol=1e-12)
    assert got.steps[1] == 0  # an inactive cell is not run
