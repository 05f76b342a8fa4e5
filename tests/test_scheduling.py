"""How the lane engine schedules cells must never change what a cell computes.

- :func:`jaxdea.sweep.schedule`: every device slice is queued lowest frequency first, and
  every cell is in it once;
- tail pools (:func:`jaxdea.protocol.lane_pools`): a batch that ends in narrower pools gives
  the same per-cell results as one pool;
- driven membranes: integrating the returned energy for the driven membranes only gives the
  same P_in as integrating it for all of them, for every drive case.

Small batches (DCDEA-LS, 60-200 Hz, few cycles) keep the compiles short.
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxdea
from jaxdea.engine.batch import (
    CPU_LANES,
    batch_cells,
    default_lanes,
    driven_membranes,
    schedule,
)
from jaxdea.engine.lanes import lane_pools, run_protocol
from jaxdea.engine.periodic import SHOOTING_LANES, shooting_lanes
from jaxdea.engine.sharding import on_accelerator
from jaxdea.studies.loadings import make_loadings
from jaxdea.studies.powermap import (
    ACCELERATOR_CHUNK_PER_DEVICE,
    ACCELERATOR_STAGE_PER_DEVICE,
    CHUNK_PER_DEVICE,
    NEIGHBOUR_STAGE_PER_DEVICE,
    chunk_target,
)

CONFIG = Path(__file__).parents[1] / "configs" / "dcdea_ls.toml"
_run = eqx.filter_jit(run_protocol)
FIELDS = ("P_out", "P_in", "P_in_signed", "amplitude", "v_rms", "status", "steps",
          "residual", "cycles_run")


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


def test_schedule_queues_each_device_lowest_frequency_first():
    rng = np.random.default_rng(3)
    freq = rng.uniform(1.0, 200.0, 11)
    for n_dev in (1, 2, 4):
        order = schedule(freq, n_dev)
        local = -(-freq.size // n_dev)
        assert order.size == local * n_dev
        slices = freq[order].reshape(n_dev, local)
        assert np.all(np.diff(slices, axis=1) >= 0), n_dev  # each queue: lowest f first
        assert set(order.tolist()) == set(range(freq.size))  # every cell, padding repeats
        # the devices get the same mix: slice k holds the frequency ranks k, k + n_dev, ...
        # (the padding repeats the highest frequency)
        ranks = np.argsort(np.argsort(freq))
        for k in range(n_dev):
            got = set(ranks[order[k * local:(k + 1) * local]].tolist())
            want = set(range(k, freq.size, n_dev))
            assert want <= got and got - want <= {freq.size - 1}, (n_dev, k)


def test_small_batches_share_a_compiled_program_and_keep_their_results(model):
    """Small batches run padded to a power of two (:func:`batch_cells`): a sweep of 5
    frequencies and a power map of 2 cells run the program a sweep of 3 compiled, and a
    cell's numbers are those it gets in a batch of another size (9 cells: 16 slots, another
    program, wider pool)."""
    assert [batch_cells(n) for n in (1, 3, 8, 9, 16, 17, 100, 128, 129, 4096)] == [
        8, 8, 8, 16, 16, 32, 128, 128, 129, 4096]
    jax.clear_caches()  # whatever ran before in this process, the first sweep traces
    traced = []

    def listen(name, secs, **kw):
        if name == "/jax/core/compile/jaxpr_trace_duration":  # (a compile may be a cache load)
            traced.append(secs)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        kw = dict(mass=2e-3, damping=0.5, cycles=6, average=2)
        three = jaxdea.sweep(model, freq=[70.0, 110.0, 160.0], **kw)
        first = sum(traced)
        traced.clear()
        five = jaxdea.sweep(model, freq=[70.0, 90.0, 110.0, 130.0, 160.0], **kw)
        # and a small power map of the same model and settings runs that program too
        small = jaxdea.powermap(model, mass=[2e-3], damping=[0.5], freq=[70.0, 160.0],
                                cycles=6, average=2, progress=False)
        again = sum(traced)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert first > 0.5 and again < 0.1 * first, (first, again)  # the engine traced once
    nine = jaxdea.sweep(model, freq=[70.0, 80.0, 90.0, 100.0, 110.0, 130.0, 150.0, 160.0,
                                     190.0], **kw)
    assert (three.status == 0).all() and (nine.status == 0).all()
    for k in ("P_out", "P_in", "amplitude", "steps"):
        for other in (five, nine):
            np.testing.assert_allclose(other[k].sel(f=three.f).values, three[k].values,
                                       rtol=1e-12, atol=0, err_msg=k)
        np.testing.assert_allclose(small[k].values.ravel(),
                                   three[k].sel(f=[70.0, 160.0]).values, rtol=1e-12, atol=0,
                                   err_msg=k)


def test_lane_pools():
    assert lane_pools(32) == (32,)
    assert lane_pools(128) == (128, 8)
    assert lane_pools(128, strict=True) == (128, 32, 8)
    # an accelerator's pool as wide as its batch shrinks as its cells finish
    assert lane_pools(250_000) == (250_000, 31_250, 4096, 8)
    assert lane_pools(5000, strict=True) == (5000, 200, 8)


class _Device:
    """What the pool-width rules read of a JAX device: its platform."""

    def __init__(self, platform: str):
        self.platform = platform


def test_pools_are_as_wide_as_the_batch_on_accelerators_only():
    cpu, gpu = (_Device("cpu"),) * 2, (_Device("cpu"), _Device("gpu"))
    assert not on_accelerator(cpu) and on_accelerator(gpu)
    assert not on_accelerator(tuple(jax.devices("cpu")))
    # CPU devices: a step's cost grows with the width, pools stay narrow
    assert default_lanes(5000, cpu) == CPU_LANES and default_lanes(40, cpu) == 40
    assert shooting_lanes(5000, cpu) == SHOOTING_LANES and shooting_lanes(8, cpu) == 8
    # accelerators: one pool as wide as the device's slice of the batch
    assert default_lanes(5000, gpu) == 5000
    assert shooting_lanes(5000, gpu) == 5000 and shooting_lanes(None, gpu) == SHOOTING_LANES


def test_chunks_are_larger_on_accelerators():
    shape, cpu, gpu = (50, 50, 996), (_Device("cpu"),) * 2, (_Device("gpu"),)
    assert chunk_target("paper", "rest", shape, cpu, None) == (2, 2 * CHUNK_PER_DEVICE, None)
    assert chunk_target("paper", "rest", shape, gpu, None) == (1, ACCELERATOR_CHUNK_PER_DEVICE,
                                                               None)
    assert chunk_target("paper", "rest", shape, gpu, 1000) == (1, 1000, None)
    # warm starts: whole masses per chunk, the chain along the dampings
    for devices, stage in ((cpu, NEIGHBOUR_STAGE_PER_DEVICE), (gpu, ACCELERATOR_STAGE_PER_DEVICE)):
        assert chunk_target("periodic", "neighbour", shape, devices, None) == (
            50 * 996, stage * len(devices) * 50, (50, 996))


def test_the_accelerator_defaults_give_the_cpu_results(model, monkeypatch):
    # a GPU user's map runs the same physics in other pools (one as wide as the chunk's
    # slice of a device, shrinking as its cells finish): run those defaults here on the CPU
    # devices, with the cascade scaled down to this small map
    kw = dict(mass=[1e-3, 2e-3, 4e-3], damping=np.geomspace(0.3, 3.0, 5),
              freq=np.linspace(100.0, 200.0, 20), progress=False)
    ref = jaxdea.powermap(model, **kw)  # 300 cells: 128-lane pools on CPU devices
    with monkeypatch.context() as mp:
        for mod in (jaxdea.engine.batch, jaxdea.engine.periodic, jaxdea.studies.powermap):
            mp.setattr(mod, "on_accelerator", lambda devices=(): True)
        mp.setattr(jaxdea.engine.lanes, "CASCADE_FROM", 16)
        assert default_lanes(150, tuple(jax.devices())) == 150  # the patches are in effect
        assert lane_pools(150) == (150, 18, 8)
        wide = jaxdea.powermap(model, **kw)
    assert (wide.status.values == 0).all() and (ref.status.values == 0).all()
    for k in ("P_out", "P_in", "amplitude"):
        np.testing.assert_allclose(wide[k].values, ref[k].values, rtol=1e-9, err_msg=k)


def test_tail_pools_do_not_change_cell_results(model):
    # mixed frequencies and dampings: cells finish at different rounds, so the narrower
    # pools take over running cells part-way through
    freq = np.array([60.0, 200.0, 75.0, 150.0, 90.0, 120.0, 66.0, 180.0, 100.0, 140.0])
    loads = make_loadings(model, 2e-3, np.linspace(0.1, 5.0, freq.size), freq)
    kw = dict(cycles=8, average=2, settle=1e-8, require_settled=False, driven=(0,))
    one = _run(model.actuator, loads, pools=(4,), **kw)
    tail = _run(model.actuator, loads, pools=(4, 2, 1), **kw)
    assert np.all(np.asarray(one.status) == 0)
    assert len(set(np.asarray(one.steps).tolist())) > 3  # cells of different lengths
    for k in FIELDS:
        np.testing.assert_allclose(np.asarray(getattr(tail, k)), np.asarray(getattr(one, k)),
                                   rtol=1e-12, atol=0, err_msg=k)
    with pytest.raises(ValueError, match="pools must be decreasing"):
        _run(model.actuator, loads, pools=(2, 4), **kw)


@pytest.mark.parametrize("drive, expect", [("A", (0,)), ("B", (1,)), ("both", (0, 1))])
def test_returned_energy_of_the_driven_membranes_only(model, drive, expect):
    loads = make_loadings(model, 2e-3, 0.1, np.array([60.0, 150.0]), drive)
    assert driven_membranes(loads) == expect
    kw = dict(cycles=6, average=2, pools=(2,))
    some = _run(model.actuator, loads, driven=expect, **kw)
    every = _run(model.actuator, loads, driven=None, **kw)
    # P_in counts no energy recovery: above the signed input power where charge went back
    # (0.7-4 % of P_in at these frequencies), so the returned energy is compared below
    p_in, signed = np.asarray(every.P_in), np.asarray(every.P_in_signed)
    assert np.all(p_in > signed * (1 + 1e-3))
    for k in FIELDS:
        np.testing.assert_allclose(np.asarray(getattr(some, k)),
                                   np.asarray(getattr(every, k)), rtol=1e-12, atol=0,
                                   err_msg=k)


def test_bad_driven_membranes_are_rejected(model):
    loads = make_loadings(model, 2e-3, 0.1, np.array([70.0]))
    for bad in ((2,), (0, 0), (-1,)):
        with pytest.raises(ValueError, match="driven must list distinct membranes"):
            run_protocol(model.actuator, loads, cycles=2, average=1, driven=bad)


def _rest(model, n):
    import jax
    import jax.numpy as jnp
    rest = model.actuator.initial_state()
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), rest)


def test_failed_cells_get_their_status_code(model):
    """Status 1 (lock-up), 2 (non-finite state), 3 (step budget) from the engine itself, and
    the ok cells of the same batch are not affected."""
    import jax.numpy as jnp
    loads = make_loadings(model, 2e-3, 0.1, np.full(5, 70.0))
    y = _rest(model, 5)
    # cell 1: dielectric dashpot stretch far below its relaxed value: the branch spring is
    # beyond its Gent limit at once; cell 2: a NaN velocity; cell 3: an infinite position
    y = eqx.tree_at(lambda s: (s.xi_m, s.v, s.q), y,
                    (y.xi_m.at[1].set(0.05), y.v.at[2].set(jnp.nan), y.q.at[3].set(jnp.inf)))
    kw = dict(cycles=3, average=1, initial=y, pools=(5,), driven=(0,))
    res = _run(model.actuator, loads, **kw)
    np.testing.assert_array_equal(np.asarray(res.status), [0, 1, 2, 2, 0])
    # cell 2's step size collapses (its NaN velocity fails every error test): it ends with its
    # whole state NaN (the lanes write that once per round, after the step that set their
    # flag); cell 3 stops at once (its Gent margin is not > 0) with its infinite state; the
    # ok cells end finite
    for leaf in jax.tree_util.tree_leaves(res.final_state):
        leaf = np.asarray(leaf).reshape(5, -1)
        assert np.isnan(leaf[2]).all() and np.isfinite(leaf[[0, 4]]).all()
    assert not np.isfinite(np.asarray(res.final_state.q)[3]).all()
    ok = _run(model.actuator, loads, cycles=3, average=1, pools=(5,), driven=(0,))
    for k in ("P_out", "P_in", "amplitude"):
        np.testing.assert_allclose(np.asarray(getattr(res, k))[[0, 4]],
                                   np.asarray(getattr(ok, k))[[0, 4]], rtol=1e-12)
    budget = _run(model.actuator, loads, control=jaxdea.StepControl(max_steps=50), **kw)
    np.testing.assert_array_equal(np.asarray(budget.status), [3, 1, 2, 2, 3])
    assert int(budget.steps[0]) == 50
