"""The papers' protocol in two passes (:mod:`jaxdea.engine.paper`): the transient without the
window's bookkeeping, then the averaged cycles from where it stopped.

- the transient pass (``run_protocol(metrics=False)``) takes the same steps to the same
  states as the full engine;
- carrying its next step over, the window's pass runs the very cycle one pass would have run
  (a fresh first step at the edge is another discretisation, visibly off the orbit);
- two passes equal one: the papers' protocol with its early exit to the exit's tolerance (a
  settled cell runs one cycle more), without it (every cell 100 cycles) to rounding;
- a cell that fails in the transient keeps its status, with NaN metrics; its neighbours in
  the batch are not affected.
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.engine.lanes import run_protocol
from jaxdea.engine.metrics import DYNAMICAL
from jaxdea.engine.paper import WINDOW_FIELDS, run_paper
from jaxdea.engine.protocols import EARLY_EXIT
from jaxdea.studies.loadings import make_loadings

CONFIG = Path(__file__).parents[1] / "configs" / "dcdea_ls.toml"
_run = eqx.filter_jit(run_protocol)
_paper = eqx.filter_jit(run_paper)
METRICS = ("P_out", "P_in", "P_in_signed", "amplitude", "v_rms", "efficiency")


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


@pytest.fixture(scope="module")
def loads(model):
    # 5 Hz and 30 Hz settle early; the lightly damped 85 Hz resonance runs all 100 cycles
    return make_loadings(model, np.array([1e-3, 1e-3, 1e-2, 3e-4]),
                         np.array([1.0, 1.0, 0.1, 3.0]), np.array([5.0, 30.0, 85.0, 160.0]))


def _dynamical(y):
    return [np.asarray(getattr(y, k)) for k in DYNAMICAL]


def test_the_transient_pass_takes_the_full_engines_steps(model, loads):
    kw = dict(cycles=12, average=1, pools=(4,))
    (lean, h), full = _run(model.actuator, loads, metrics=False, **kw), _run(
        model.actuator, loads, **kw)
    for k in ("steps", "cycles_run", "status", "residual"):
        np.testing.assert_array_equal(np.asarray(getattr(lean, k)), np.asarray(getattr(full, k)))
    for a, b in zip(jax.tree_util.tree_leaves(lean.final_state),
                    jax.tree_util.tree_leaves(full.final_state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.all(np.asarray(h) > 0) and np.all(np.asarray(h) <= 1e-3)  # dt_max


def test_the_window_pass_runs_the_cycle_one_pass_would_have_run(model, loads):
    lean, h = _run(model.actuator, loads, cycles=20, average=1, pools=(4,), metrics=False)
    on = _run(model.actuator, loads, cycles=1, average=1, pools=(4,),
              initial=lean.final_state, initial_step=h)
    one = _run(model.actuator, loads, cycles=21, average=1, pools=(4,))
    np.testing.assert_array_equal(np.asarray(lean.steps) + np.asarray(on.steps),
                                  np.asarray(one.steps))
    for a, b in zip(_dynamical(on.final_state), _dynamical(one.final_state)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)
    for k in METRICS + ("residual",):
        np.testing.assert_allclose(np.asarray(getattr(on, k)), np.asarray(getattr(one, k)),
                                   rtol=1e-9, err_msg=k)
    # a fresh first step (T / 200) at the cycle's first edge: another discretisation, whose
    # orbit the cell then drifts to; its residual is far above the carried-on cycle's
    fresh = _run(model.actuator, loads, cycles=1, average=1, pools=(4,),
                 initial=lean.final_state)
    # (30 Hz: 1.7e-14 carried on, 5.8e-7 fresh, with as many steps)
    res_on, res_fresh = np.asarray(on.residual)[1], np.asarray(fresh.residual)[1]
    assert res_on < 1e-12 and res_fresh > 1e-8, (res_on, res_fresh)


def test_two_passes_equal_one(model, loads):
    kw = dict(cycles=100, average=5, pools=(4,))
    # with the early exit: the metrics to the exit's tolerance, a settled cell one cycle more
    one = _run(model.actuator, loads, settle=EARLY_EXIT, require_settled=False, **kw)
    two = _paper(model.actuator, loads, settle=EARLY_EXIT, **kw)
    c1, c2 = np.asarray(one.cycles_run), np.asarray(two.cycles_run)
    np.testing.assert_array_equal(np.asarray(two.status), 0)
    settled = c1 < 95
    assert settled[[0, 1]].all() and not settled[2], c1
    np.testing.assert_array_equal(c2, np.where(settled, c1 + 1, c1))
    for k in METRICS:
        np.testing.assert_allclose(np.asarray(getattr(two, k)), np.asarray(getattr(one, k)),
                                   rtol=1e-6, err_msg=k)
    # a cell that never settles runs the same cycles and averages the same last 5
    for k in METRICS:
        np.testing.assert_allclose(np.asarray(getattr(two, k))[2],
                                   np.asarray(getattr(one, k))[2], rtol=1e-11, err_msg=k)
    # every cell all 100 cycles: the same run, rounding aside (the window's energies
    # restart from zero)
    one = _run(model.actuator, loads, **kw)
    two = _paper(model.actuator, loads, **kw)
    np.testing.assert_array_equal(np.asarray(two.steps), np.asarray(one.steps))
    np.testing.assert_array_equal(np.asarray(two.cycles_run), 100)
    for k in METRICS:
        np.testing.assert_allclose(np.asarray(getattr(two, k)), np.asarray(getattr(one, k)),
                                   rtol=1e-11, err_msg=k)


def test_a_cell_that_fails_in_the_transient_keeps_its_status_with_nan_metrics(model):
    loads = make_loadings(model, 2e-3, 0.1, np.full(4, 70.0))
    rest = model.actuator.initial_state()
    y = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (4,) + a.shape), rest)
    # cell 1 beyond its Gent limit at once (lock-up), cell 2 with a NaN velocity
    y = eqx.tree_at(lambda s: (s.xi_m, s.v), y, (y.xi_m.at[1].set(0.05), y.v.at[2].set(jnp.nan)))
    kw = dict(cycles=12, average=2, initial=y, pools=(4,), settle=EARLY_EXIT)
    two = _paper(model.actuator, loads, **kw)
    one = _run(model.actuator, loads, require_settled=False, **kw)
    np.testing.assert_array_equal(np.asarray(two.status), [0, 1, 2, 0])
    for k in WINDOW_FIELDS:
        v = np.asarray(getattr(two, k))
        assert np.isnan(v[[1, 2]]).all() and np.isfinite(v[[0, 3]]).all(), k
        np.testing.assert_allclose(v[[0, 3]], np.asarray(getattr(one, k))[[0, 3]], rtol=1e-6)


def test_jumps_in_the_transient_keep_the_early_exits_answers(model, loads):
    """``StepControl(extrapolate=1e-8)`` (what ``"auto"`` picks for a big map): a cell whose
    transient fits its recurrence jumps to :data:`~jaxdea.engine.extrapolate.LOOKAHEAD`
    cycles short of the transient pass's end, with the step size of its last cycle end, and
    integrates on from there as any cell: its early exit finds it periodic, or (as these
    cells, whose transient decays by a few per cent a cycle) it runs the transient pass's
    end and the last 5 cycles. 8 lightly damped cells at 60-200 Hz give the answers of the
    run without jumps (measured on 1024 cells at 1-200 Hz: P_out within 1.4e-6, the
    amplitude 7.2e-6; on the 250 000 cells of the map's slice, P_out 5.1e-6) in fewer steps.
    Without an early exit nothing jumps."""
    rng = np.random.default_rng(2)
    n = 8
    cells = make_loadings(model, 10 ** rng.uniform(-3, -2, n), 10 ** rng.uniform(-1, -0.3, n),
                          rng.uniform(60.0, 200.0, n))
    kw = dict(cycles=100, average=5, pools=(n,), settle=EARLY_EXIT)
    plain = _paper(model.actuator, cells, **kw)
    jumped = _paper(model.actuator, cells, control=jaxdea.StepControl(extrapolate=1e-8), **kw)
    np.testing.assert_array_equal(np.asarray(jumped.status), np.asarray(plain.status))
    np.testing.assert_array_equal(np.asarray(plain.status), 0)
    fewer = np.asarray(jumped.steps) < 0.8 * np.asarray(plain.steps)
    assert fewer.sum() >= n // 2, (np.asarray(jumped.steps), np.asarray(plain.steps))
    # a jumped cell's cycles count from its landing (the transient pass's 95 cycles land
    # at 89): at least one cycle after it
    ran = np.asarray(jumped.cycles_run)[fewer]
    assert (ran >= 90).all(), ran
    for k, tol in (("P_out", 1e-5), ("P_in", 1e-5), ("v_rms", 1e-5), ("amplitude", 1e-4)):
        np.testing.assert_allclose(np.asarray(getattr(jumped, k)),
                                   np.asarray(getattr(plain, k)), rtol=tol, err_msg=k)
    strict = dict(cycles=100, average=5, pools=(4,))
    a = _paper(model.actuator, loads, **strict)
    b = _paper(model.actuator, loads, control=jaxdea.StepControl(extrapolate=1e-8), **strict)
    np.testing.assert_array_equal(np.asarray(b.steps), np.asarray(a.steps))
