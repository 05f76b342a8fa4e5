"""The papers' protocol in two passes: the transient without the window's bookkeeping.

A cell of the papers' protocol (``cycles`` periods from rest, the mean of the last
``average``; with the early exit :data:`~jaxdea.engine.protocols.EARLY_EXIT` a cell stops at
the first cycle end where it repeats its last cycle, and that cycle is averaged) spends most
of its steps in a transient whose metrics nobody reads: at 100 Hz a cell settles after ~55
cycles and one is averaged. The lane step's window bookkeeping (payload extrema from the
Hermite interpolant, the energy returned to the source, the window's records) is ~30 % of
its cost, and in a pool of lanes it cannot be skipped per lane. So :func:`run_paper` runs

1. **the transient**, :func:`~jaxdea.engine.lanes.run_protocol` with ``metrics=False``, for
   at most ``cycles - average`` cycles, each cell stopping where the early exit stops it;
2. **the window**, from each cell's last state with the full bookkeeping: one more cycle
   where the cell settled in the first pass, its last ``average`` cycles (with the early
   exit) where it did not.

A settled cell thus runs one cycle more than in one pass, and its metrics are over the
cycle after the one that met the early exit (the same to the early exit's tolerance); a
cell that never settles runs the same ``cycles`` cycles and averages the same last
``average``. A cell that fails in the transient (lock-up, a non-finite state, the step
budget) keeps that status, with NaN metrics (there is no window to average). Step budgets
(``StepControl.max_steps``) count per pass. With ``StepControl(extrapolate=...)`` (a
tolerance: the studies resolve ``"auto"``) a cell of the transient's pass may jump ahead
(:mod:`jaxdea.engine.extrapolate`): to :data:`~jaxdea.engine.extrapolate.LOOKAHEAD` cycles
before the end of that pass, with the step size of its last cycle end, where its early
exit then finds it periodic; the window's pass never jumps. A jumped cell's
``cycles_run`` counts the cycles jumped over.

Measured (``docs/performance.md``): the transient's lane-step 0.70x the full one's (1024
DCDEA-LS cells at 20-200 Hz, one device, the same steps bit for bit).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..models.cone import ConeActuator, Loading
from .lane_state import first_step, rest_states, select_cells
from .lanes import LONG_ROUND, batch_pools, may_jump, run_protocol
from .metrics import CycleMetrics
from .step_control import StepControl

#: The metrics a cell that failed in the transient reports as NaN.
WINDOW_FIELDS = ("P_out", "P_in", "P_in_signed", "efficiency", "amplitude", "v_rms")


def run_paper(model: ConeActuator, loadings: Loading, *, cycles, average,
              control: StepControl = StepControl(), lanes: int | None = None,
              initial=None, active=None, settle: float | None = None,
              pools: tuple[int, ...] | None = None,
              driven: tuple[int, ...] | None = None) -> CycleMetrics:
    """The papers' protocol on a batch of independent cells, in two passes (the module's
    docstring). Jittable.

    **Arguments:**

    - `model`, `loadings`: the cone and its cells (leading axis = cells).
    - `cycles`, `average`: periods per cell and how many of the last are averaged (integers,
      or integer arrays: traced, one compiled program for every count).
    - `control`, `lanes`, `pools`, `driven`: as for
      :func:`~jaxdea.engine.lanes.run_protocol`.
    - `initial`: start states (leading axis = cells; default rest).
    - `active`: bool per cell, run only these (default all).
    - `settle`: the early exit's tolerance, or None (every cell runs all its cycles).

    **Returns:**

    :class:`~jaxdea.engine.metrics.CycleMetrics` per cell; ``steps`` and ``cycles_run``
    count both passes.
    """
    common = dict(control=control, lanes=lanes, settle=settle, require_settled=False,
                  pools=pools, driven=driven)
    n = jax.tree_util.tree_leaves(loadings)[0].shape[0]
    if initial is None:  # rest, explicit: the window's pass starts from it where the
        initial = rest_states(model, loadings)  # transient's does not run
    cycles, average = jnp.asarray(cycles, jnp.int32), jnp.asarray(average, jnp.int32)
    transient, one = cycles - average, jnp.ones_like(cycles)
    run_a = jnp.broadcast_to(transient >= 1, (n,))
    if active is not None:
        run_a = run_a & jnp.asarray(active, bool)
    # rounds of LONG_ROUND steps, or of 16 where the transient may jump: its records take one
    # cycle-start state a round, and a lane that ends two cycles in one round misses one
    rounds = 16 if may_jump(control, settle, require_settled=False) else LONG_ROUND
    first, h = run_protocol(model, loadings, cycles=jnp.maximum(transient, 1), average=one,
                            initial=initial, active=run_a, metrics=False,
                            steps_per_round=rounds, **common)
    failed = run_a & (first.status != 0)
    # stopped before its budget with status 0: the early exit met (never without `settle`)
    settled = run_a & (first.status == 0) & (first.cycles_run < transient)
    window = jnp.where(settled, 1, average)
    # the transient's next step carries on (the cycle it ends is then the one it would have
    # run, bit for bit); a fresh first step at the edge is another discretisation, whose
    # orbit lies ~4e-5 (scaled) away and takes the transient's decay to reach
    step = jnp.where(run_a, h, first_step(control.dt_max, loadings.drive.frequency))
    run_b = ~failed if active is None else ~failed & jnp.asarray(active, bool)
    # one cycle a cell (k where unsettled), the lowest frequencies queued first: no long
    # tail, so without the narrowest pool (each pool is a compile of its own)
    full = pools or batch_pools(n, lanes, strict=settle is None)
    second = run_protocol(model, loadings, cycles=window, average=window,
                          initial=select_cells(run_a, first.final_state, initial),
                          initial_step=step, active=run_b, steps_per_round=LONG_ROUND,
                          **{**common, "pools": tuple(full[:-1]) or tuple(full),
                             "control": control._replace(extrapolate=None)})
    out = {}
    for k in CycleMetrics.__dataclass_fields__:
        a, b = getattr(first, k), getattr(second, k)
        if k in ("steps", "cycles_run"):
            out[k] = jnp.where(run_a, a, 0) + b
        elif k in WINDOW_FIELDS:
            out[k] = jnp.where(failed, jnp.nan, b)
        else:
            out[k] = select_cells(failed, a, b)
    return CycleMetrics(**out)
