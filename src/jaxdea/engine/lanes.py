"""The papers' protocol on a batch of cells: N drive cycles from rest, average the last k.

One jitted computation runs every cell of a batch (any mix of frequencies, payloads, phases).

Lanes and a queue: a 1 Hz cell needs ~100x the steps of a 200 Hz cell, so cells are not tied
to vmap lanes. A fixed pool of lanes works through a queue of cells; a lane that finishes its
cell takes the next one. Work stays balanced whatever the frequency mix. (Plain vmap of
per-cell loops would run every lane as long as the slowest cell.) When the queue is empty
and only a few cells are left, they move into a narrower pool (:func:`lane_pools`): a step
costs about the same for a busy lane as for an idle one, so a wide pool that finishes one
long cell would pay its full width for every step of it.

Time stepping: adaptive steps of :class:`jaxdea.solver.LawsonRK4` (RC charging exact, RK4
with an embedded order-3 error estimate for the rest; or Krogstad's
:class:`~jaxdea.solver.ExponentialRK4` with ``StepControl(solver="exponential")``), standard
I-controller on the scaled RMS error: :class:`~jaxdea.engine.step_control.IController`).
Steps never cross a square-wave edge or a cycle boundary: each lane clips its step to the
next node of its cell's cycle (all edges, any relative phase, and the period end), so no
edge is found by rejection. Energies are ODE states; the window average is the
difference of their values at the window ends, so nothing is stored per step. The payload
amplitude over the window is the extremum of the cubic Hermite interpolant of every
accepted step (position and velocity at both ends).

Beyond "N cycles from rest" the same engine runs the other protocols' building blocks:

- ``initial``: per-cell start states (periodic shooting starts each cell from its iterate);
- ``successor``: chains of cells; a lane that finishes a cell goes on with its successor from
  the final state (frequency continuation, paper 000's forward sweep); the queue holds the
  chain heads only;
- ``active``: run only these cells (the others are skipped at no cost);
- ``settle``: stop a cell as soon as its one-period map has converged (residual below
  ``settle``, after correcting for the observed contraction rate), metrics over its last cycle.
  With ``require_settled=False`` this is the papers' protocol with an early exit: a cell
  whose trajectory is already periodic to ``settle`` would only repeat its last cycle until
  cycle N, so it stops there (a cell that never settles runs all N cycles and averages the
  last k as usual).

Every cell also reports its periodicity residual: the scaled max-norm of the change of the
dynamical state over the last cycle (:func:`~jaxdea.engine.metrics.periodicity_residual`).

Status codes per cell: :data:`~jaxdea.engine.metrics.STATUS`; the per-cell metrics and
their pieces are in :mod:`jaxdea.engine.metrics`, the step-size control in
:mod:`jaxdea.engine.step_control`. The engine reaches the model only through its contract
(vector field, linearisation, :meth:`~jaxdea.models.cone.ConeActuator.payload_motion`,
:meth:`~jaxdea.models.cone.ConeActuator.lockup_margin`,
:meth:`~jaxdea.models.cone.ConeActuator.returned_energy`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..models.cone import ConeActuator, ConeState, Loading
from ..solver import ExponentialRK4, LawsonRK4, SemilinearTerm
from . import extrapolate as _extrapolate
from .lane_state import (
    Lane,
    cycle_nodes,
    first_step,
    reset_accumulators,
    rest_states,
    scatter_each,
    select_cells,
)
from .metrics import (
    CycleMetrics,
    all_finite,
    dynamics,
    energies,
    hermite_extrema,
    periodicity_residual,
    settled,
    window_metrics,
)
from .precision import SINGLE_CHARGE_WEIGHT_MIN, narrow, narrow_states, widen_states
from .step_control import IController, StepControl, charge_weight

#: Smallest lane pool that gets a smaller pool for the end of its batch (:func:`lane_pools`).
TAIL_FROM = 64
#: Pools at least twice this wide end in a cascade of pools, each 1/:data:`CASCADE` of the
#: one before, down to this width (:func:`lane_pools`). Only the accelerators' default pools
#: are this wide (:func:`jaxdea.engine.batch.default_lanes`): there a step of 10^5 lanes is bound by
#: memory traffic, so finished lanes cost as much as busy ones, while below a few thousand
#: lanes a step costs its kernel launches whatever the width.
CASCADE_FROM = 4096
CASCADE = 8
#: Steps per round (between two queue updates) of the papers' protocol's passes that do not
#: jump (:func:`jaxdea.engine.paper.run_paper`); 16 (:func:`run_protocol`'s default) where
#: the transient may jump (its records take one cycle start a round) and elsewhere. A round
#: costs about a step and a half: 0.91x without jumps, the same results bit for bit
#: (``bench/NOTES.md``).
LONG_ROUND = 32
#: Narrowest lane pool. XLA compiles a vmap of width 1 to scalar code that rounds differently
#: from the vector code of every wider pool, so a cell run alone (a one-cell chunk per
#: device, a one-frequency sweep) got other last bits than in company, and a chaotic cell a
#: different answer (measured: widths 2-128 bit-identical, width 1 not). A 1-cell batch
#: runs with one idle lane instead.
MIN_LANES = 2


def lane_pools(n_lanes: int, strict: bool = False) -> tuple[int, ...]:
    """The lane pools a batch runs through, widest first.

    ``n_lanes`` while the queue lasts, then 8 lanes for its last cells. ``strict`` (every
    cell runs all its cycles): a middle pool of ``sqrt(8 n_lanes)`` lanes in between, because
    there the lowest frequencies form a long tail of long cells rather than a few outliers.
    A pool of at least twice :data:`CASCADE_FROM` lanes (an accelerator's, as wide as the
    batch) first shrinks by :data:`CASCADE` at a time down to that width, as its cells finish.
    Each pool is one more compiled loop, so pools under :data:`TAIL_FROM` lanes keep one.
    The measurements behind these choices are in ``bench/NOTES.md``.

    **Arguments:**

    - `n_lanes`: the widest pool (lanes per device).
    - `strict`: whether every cell runs all its cycles (no early exit).

    **Returns:**

    The pool widths, decreasing.
    """
    if n_lanes < TAIL_FROM:
        return (n_lanes,)
    wide = [n_lanes]
    while wide[-1] >= 2 * CASCADE_FROM:
        wide.append(max(wide[-1] // CASCADE, CASCADE_FROM))
    n = wide.pop()
    if strict:
        return (*wide, n, round(math.sqrt(8 * n)), 8)
    return (*wide, n, 8)


def may_jump(control: StepControl, settle: float | None, require_settled: bool) -> bool:
    """Whether :func:`run_protocol`'s transient may jump (``StepControl.extrapolate``): a
    tolerance given, with an early exit (``settle``) that does not require settling."""
    return (settle is not None and not require_settled
            and not isinstance(control.extrapolate, str | None))


def batch_pools(n_cells: int, lanes: int | None = None, strict: bool = False) -> tuple[int, ...]:
    """The default pools of a batch of ``n_cells`` cells (per device) with ``lanes`` lanes
    (default 32): :func:`lane_pools` of the narrower of the two."""
    return lane_pools(int(min(n_cells, lanes or 32)), strict=strict)


def run_protocol(
    model: ConeActuator,
    loadings: Loading,
    *,
    cycles: int = 100,
    average: int = 5,
    control: StepControl = StepControl(),
    lanes: int | None = None,
    steps_per_round: int = 16,
    initial: ConeState | None = None,
    initial_step: Array | None = None,
    successor: Array | None = None,
    active: Array | None = None,
    settle: float | None = None,
    require_settled: bool = True,
    pools: tuple[int, ...] | None = None,
    driven: tuple[int, ...] | None = None,
    frozen_steps: bool = False,
    metrics: bool = True,
) -> CycleMetrics | tuple[CycleMetrics, Array]:
    """Run ``cycles`` periods from rest for every cell of ``loadings`` (leading axis = cells)
    and average the last ``average`` periods. Jittable; ``model`` is shared by all cells.

    ``lanes``: size of the lane pool (default 32; callers queue cells in a useful order,
    e.g. :func:`jaxdea.sweep.schedule`, and pick the width, e.g.
    :func:`jaxdea.sweep.default_lanes`); ``steps_per_round``: steps between two queue
    updates.

    ``initial``: start state of every cell (leading axis = cells; default: rest at the static
    equilibrium). ``successor``: int per cell, the cell that continues from this cell's final
    state (accumulators reset, drive restarted at t = 0), or ``n_cells`` for none; chain heads
    start from ``initial``. ``active``: bool per cell; inactive cells are not run and their
    outputs are zeros. ``settle``: if given, a cell stops at the first cycle end where its
    periodicity residual (corrected for the observed contraction) is below ``settle``; its
    metrics are then over that last cycle. A cell that reaches ``cycles`` without settling
    averages its last ``average`` cycles and gets status 4 if ``require_settled`` (periodic
    steady states), else the ordinary status (the papers' protocol with an early exit).

    ``cycles`` and ``average`` may be integer arrays (traced under jit: one compiled engine
    for every cycle count; their range is then the caller's to check), one per cell
    (``(n_cells,)``) or one for all.

    ``pools``: the lane-pool sizes the batch runs through, widest first (default
    :func:`lane_pools`; the first entry replaces ``lanes``). ``driven``: the membranes whose
    source voltage is non-zero in some cell (static; default all). The energy returned to
    the source is integrated for these only (for two membranes ~20 % of a lane-step).

    ``frozen_steps``: differentiated, the step sizes count as constants (no tangent through
    the error estimate into the controller): a shot's Jacobian at 0.55x the cost, too coarse
    for design gradients (``bench/NOTES.md``; :func:`~jaxdea.engine.periodic.shoot_period`).

    ``initial_step``: per cell, the first step to try, s (default ``min(dt_max, T / 200)``).
    ``metrics=False``: the transient only (:mod:`jaxdea.engine.paper`): no window bookkeeping
    (payload extrema, returned energy, window records; 0.70x the lane-step), so the outputs'
    metrics are meaningless (final states, residuals, statuses and counts are as usual);
    returns ``(metrics, h)``, ``h`` each cell's next step (its ``initial_step`` to go on).
    """
    if isinstance(cycles, int) and isinstance(average, int):
        if not 1 <= average <= cycles:
            raise ValueError(
                f"need integers 1 <= average <= cycles, got average={average}, cycles={cycles}"
            )
    elif not (hasattr(cycles, "dtype") and hasattr(average, "dtype")):
        raise ValueError(f"cycles and average must be integers, got {cycles!r}, {average!r}")
    n_cells = jax.tree_util.tree_leaves(loadings)[0].shape[0]
    budget = jnp.broadcast_to(jnp.asarray(cycles, jnp.int32), (n_cells,))
    average_of = jnp.broadcast_to(jnp.asarray(average, jnp.int32), (n_cells,))
    if pools is None:
        pools = batch_pools(n_cells, lanes, strict=settle is None)
    if not pools or any(p < 1 for p in pools) or list(pools) != sorted(pools, reverse=True):
        raise ValueError(f"pools must be decreasing positive lane counts, got {pools!r}")
    pools = tuple(dict.fromkeys(max(MIN_LANES, int(min(n_cells, p))) for p in pools))
    n_lanes = pools[0]
    if driven is None:
        driven = tuple(range(model.n_membranes))
    driven = tuple(sorted(int(j) for j in driven))
    if any(not 0 <= j < model.n_membranes for j in driven) or len(set(driven)) < len(driven):
        raise ValueError(f"driven must list distinct membranes in [0, {model.n_membranes}), "
                         f"got {driven!r}")
    n_driven = len(driven)
    # static selection of the driven membranes: a slice when they are contiguous
    on = (slice(driven[0], driven[-1] + 1) if driven and driven == tuple(
        range(driven[0], driven[-1] + 1)) else np.asarray(driven, dtype=int))
    solver = ExponentialRK4() if control.solver == "exponential" else LawsonRK4()
    controller = IController(rtol=control.rtol, dt_max=control.dt_max)
    if initial is None and loadings.payload.loads_at_rest:  # a weight or a preloaded spring
        initial = rest_states(model, loadings)
    y0 = model.initial_state()
    precision = control.precision
    if precision == "single":  # the rest states above are float64; the lanes narrow them
        model = narrow(model)
        loadings = eqx.tree_at(lambda ld: ld.payload, loadings, narrow(loadings.payload))
        y0 = narrow_states(y0)
        initial = None if initial is None else narrow_states(initial)
    term = SemilinearTerm(lambda t, y, a: _vector_field(model, t, y, a), model.linearisation)
    # the transient's extrapolation (StepControl.extrapolate, a tolerance; "auto" is the
    # studies' to resolve, off here): runs with an early exit of the papers' and the
    # continuation protocol only (not the periodic protocol's settling, nor one-period shots)
    jump = control.extrapolate if may_jump(control, settle, require_settled) else None
    if isinstance(cycles, int) and isinstance(average, int) and \
            _extrapolate.landing_cycle(cycles, average) < _extrapolate.HISTORY + 1:
        jump = None
    if jump is not None and (jnp.ndim(cycles) or jnp.ndim(average)):
        raise ValueError("StepControl.extrapolate needs one cycles/average for all cells")
    # per-lane shapes of the extrapolation's records: empty when it is off
    hist_shape = (_extrapolate.HISTORY, _extrapolate.flatten(y0).size) if jump is not None \
        else (0, 0)
    count_shape = () if jump is not None else (0,)

    def charge_error_weight(lane: Lane):
        """The charge's error weight of the lane's cell (``step_control.charge_weight``); in
        single precision at least :data:`~jaxdea.engine.precision.SINGLE_CHARGE_WEIGHT_MIN`."""
        w = charge_weight(lane.loading.drive.frequency)
        return jnp.maximum(w, SINGLE_CHARGE_WEIGHT_MIN) if precision == "single" else w

    succ = (jnp.full(n_cells, n_cells, jnp.int32) if successor is None
            else jnp.asarray(successor, jnp.int32))
    is_head = jnp.ones(n_cells, bool).at[succ].set(False, mode="drop")
    if active is not None:
        is_head = is_head & jnp.asarray(active, bool)
    queue = jnp.nonzero(is_head, size=n_cells, fill_value=n_cells)[0]
    queue = jnp.concatenate([queue, jnp.full(n_lanes, n_cells, queue.dtype)])

    def start_state(idx: Array) -> ConeState:
        """Start states of cells ``idx`` (one per lane)."""
        if initial is None:
            return jax.tree_util.tree_map(
                lambda a: jnp.broadcast_to(a, idx.shape + a.shape), y0)
        safe = jnp.minimum(idx, n_cells - 1)
        return reset_accumulators(jax.tree_util.tree_map(lambda a: a[safe], initial))

    def fresh(idx: Array, y: ConeState) -> Lane:
        """Lanes starting cell ``idx`` from ``y`` (``idx >= n_cells``: idle lane)."""
        safe = jnp.minimum(idx, n_cells - 1)
        loading = jax.tree_util.tree_map(lambda a: a[safe], loadings)
        period = 1.0 / loading.drive.frequency
        n = idx.shape[0]
        return Lane(
            job=jnp.where(idx < n_cells, idx, n_cells),
            y=y,
            loading=loading,
            nodes=jax.vmap(cycle_nodes)(loading),
            cycle=jnp.zeros(n, jnp.int32),
            budget=budget[safe],
            average=average_of[safe],
            u=jnp.zeros(n),
            h=(first_step(control.dt_max, loading.drive.frequency) if initial_step is None
               else jnp.asarray(initial_step, period.dtype)[safe]),
            steps=jnp.zeros(n, jnp.int32),
            window=energies(y),
            wcycle=jnp.zeros(n, jnp.int32),
            prev=dynamics(y),
            res=jnp.full(n, jnp.inf),
            ratio=jnp.ones(n),
            rate=jnp.ones(n),
            back=jnp.zeros((n, n_driven)),
            xmin=jnp.full(n, jnp.inf),
            xmax=jnp.full(n, -jnp.inf),
            lockup=jnp.zeros(n, bool),
            blown=jnp.zeros(n, bool),
            done=idx >= n_cells,
            history=jnp.zeros((n,) + hist_shape),
            recorded=jnp.full((n,) + count_shape, -1, jnp.int32),
            streak=jnp.zeros((n,) + count_shape, jnp.int32),
            origin=jnp.zeros((n,) + hist_shape[1:]),
            landing=jnp.zeros((n,) + hist_shape[1:]),
            jumped_from=jnp.full((n,) + count_shape, -1, jnp.int32),
            expect=jnp.zeros((n,) + count_shape),
            guess=jnp.zeros((n,) + hist_shape[1:]),
            guessed=jnp.full((n,) + count_shape, -1, jnp.int32),
            hwrap=jnp.zeros((n,) + count_shape),
        )

    def load(lane: Lane, idx: Array, y: ConeState, mask: Array) -> Lane:
        """Give the lanes in ``mask`` cell ``idx`` starting from ``y``; the others keep theirs."""
        return select_cells(mask, fresh(idx, y), lane)

    def lane_step(lane: Lane) -> Lane:
        """One attempted adaptive step of one lane (vmapped), then the bookkeeping."""
        period = 1.0 / lane.loading.drive.frequency
        target = jnp.min(jnp.where(lane.nodes > lane.u + 1e-12, lane.nodes, 1.0))
        to_node = (target - lane.u) * period
        clipped = lane.h >= to_node
        h = jnp.where(clipped, to_node, lane.h)
        # time within the current cycle: the drive is periodic, and an absolute time of
        # many periods loses the stage times' 1e-9 h nudge off an edge to rounding (at t ~ 4 s
        # one ulp is 9e-16 s, the nudge of a 1 us step 1e-15 s), so a step just after an edge
        # saw the drive of the other side: cycle-start charges of 1e-9 C where they are 0,
        # residuals of 1e-5-1e-3 by cycle 60-100 on a cell periodic to 1e-12 at cycle 40
        t0 = lane.u * period
        y1, err, *_ = solver.step(term, t0, t0 + h, lane.y, lane.loading, None, False)
        active = ~lane.done
        # frozen_steps: no tangent through the step-size choice (a shot's Jacobian)
        judged = jax.lax.stop_gradient((lane.y, y1, err)) if frozen_steps else (lane.y, y1, err)
        accept, ok, h_next = controller.adapt_step_size(*judged, h, lane.h, clipped, active,
                                                        charge_error_weight(lane))

        y = jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), y1, lane.y)
        u = jnp.where(accept, jnp.where(clipped, target, lane.u + h / period), lane.u)
        wrap = u >= 1.0 - 1e-12
        cycle = lane.cycle + wrap.astype(jnp.int32)
        u = jnp.where(wrap, 0.0, u)

        # periodicity residual at each cycle end, and its contraction per cycle
        res = periodicity_residual(y, lane.prev)
        measured = wrap & jnp.isfinite(lane.res)
        ratio = jnp.where(measured, res / jnp.maximum(lane.res, 1e-300), lane.ratio)
        rate = jnp.where(measured, jnp.maximum(ratio, lane.ratio), lane.rate)  # last two cycles
        res = jnp.where(wrap, res, lane.res)
        # only what is read later is carried: the dynamical states here, the energies in
        # the window (each leaf selected is a kernel per lane-step)
        prev = jax.tree_util.tree_map(lambda a, b: jnp.where(wrap, a, b), dynamics(y),
                                      lane.prev)

        # window bookkeeping: amplitude from the Hermite interpolant of the accepted step
        if settle is None:
            in_window = accept & (lane.cycle >= lane.budget - lane.average)
        else:
            in_window = accept
        if settle is None:
            start = wrap & (cycle == lane.budget - lane.average)
            converged = jnp.zeros_like(wrap)
        else:  # the window is the cycle just finished; restart it unless the cell is done
            # or the last `average` cycles of the budget have begun
            converged = wrap & (cycle >= 2) & settled(res, rate, settle)
            start = wrap & ~converged & (cycle <= lane.budget - lane.average)
        if metrics:
            (x0, v0), (x1, v1) = model.payload_motion(lane.y), model.payload_motion(y1)
            lo, hi = hermite_extrema(x0, v0, x1, v1, h)
            xmin = jnp.where(in_window, jnp.minimum(lane.xmin, lo), lane.xmin)
            xmax = jnp.where(in_window, jnp.maximum(lane.xmax, hi), lane.xmax)
            # charge pushed back into the source during the step (Phi is constant within a
            # step), for the driven membranes only (an undriven one has Phi = 0)
            back = model.returned_energy(t0, h, lane.y, y1, lane.loading, on)
            back = jnp.where(in_window, lane.back + back, lane.back)
            if settle is not None:
                xmin = jnp.where(start, jnp.inf, xmin)
                xmax = jnp.where(start, -jnp.inf, xmax)
                back = jnp.where(start, 0.0, back)
            window = jax.tree_util.tree_map(lambda a, b: jnp.where(start, a, b), energies(y),
                                            lane.window)
            wcycle = jnp.where(start, cycle, lane.wcycle)
        else:
            xmin, xmax, back, window, wcycle = (lane.xmin, lane.xmax, lane.back, lane.window,
                                                lane.wcycle)

        margin = model.lockup_margin(y)
        lockup = lane.lockup | (active & ~(margin > 0))
        steps = lane.steps + active.astype(jnp.int32)
        # step size collapsed: non-finite/unstable. The lane stops here; its state is set
        # to NaN once per round (in round_), not in every step (8 selects per step)
        blown = active & ~ok & (h < 1e-12 * period)
        done = (lane.done | (cycle >= lane.budget) | lockup | blown | (steps >= control.max_steps)
                | converged)
        if jump is not None:  # the step a jump's landing goes on with (a cycle's first)
            lane = eqx.tree_at(lambda s: s.hwrap, lane, jnp.where(wrap, h_next, lane.hwrap))
        return eqx.tree_at(
            lambda s: (s.y, s.cycle, s.u, s.h, s.steps, s.window, s.wcycle, s.prev, s.res,
                       s.ratio, s.rate, s.back, s.xmin, s.xmax, s.lockup, s.blown, s.done),
            lane, (y, cycle, u, h_next, steps, window, wcycle, prev, res, ratio, rate, back,
                   xmin, xmax, lockup, lane.blown | blown, done),
        )

    out = dict(
        **({} if metrics else {"h": jnp.zeros(n_cells)}),  # the transient's next step
        P_out=jnp.zeros(n_cells), P_in=jnp.zeros(n_cells), P_in_signed=jnp.zeros(n_cells),
        efficiency=jnp.zeros(n_cells), amplitude=jnp.zeros(n_cells), v_rms=jnp.zeros(n_cells),
        status=jnp.zeros(n_cells, jnp.int32), steps=jnp.zeros(n_cells, jnp.int32),
        residual=jnp.zeros(n_cells), cycles_run=jnp.zeros(n_cells, jnp.int32),
        final_state=jax.tree_util.tree_map(
            lambda a: jnp.zeros((n_cells,) + a.shape, jnp.float64), y0),
    )

    def harvest(out, lane: Lane, finished: Array):
        """Write the finished lanes' results into the outputs (other lanes write nowhere)."""
        values = jax.vmap(lambda ln: window_metrics(ln, ln.budget, settle, require_settled))(
            lane)
        values["final_state"] = widen_states(lane.y)
        if not metrics:
            values["h"] = lane.h
        target = jnp.where(finished, lane.job, n_cells)  # index n_cells is dropped
        return scatter_each(out, target, values)

    def round_(carry):
        lane, out, next_job = carry
        lane = jax.lax.fori_loop(0, steps_per_round, lambda _, ln: jax.vmap(lane_step)(ln), lane)
        # a lane whose step size collapsed ends with its whole state NaN (set here once per
        # round, not in every step)
        nans = jax.tree_util.tree_map(lambda a: jnp.full_like(a, jnp.nan), lane.y)
        lane = eqx.tree_at(lambda s: s.y, lane, select_cells(lane.blown, nans, lane.y))
        if jump is not None:
            lane, want = _extrapolate.record(lane, cycles, average)
            lane = jax.lax.cond(jnp.any(want), lambda ln, w: select_cells(
                *_extrapolate.jump(ln, w, cycles, average, jump)), lambda ln, _: ln,
                lane, want)
            lane = jax.lax.cond(jnp.any(lane.jumped_from >= 0), lambda ln: select_cells(
                *_extrapolate.verify(ln, cycles, average, jump)), lambda ln: ln, lane)
        finished = lane.done & (lane.job < n_cells)
        out = harvest(out, lane, finished)
        # a finished cell's successor goes on from its final state; other lanes take the
        # next chain head from the queue
        nxt = succ[jnp.minimum(lane.job, n_cells - 1)]
        chained = finished & (nxt < n_cells)
        from_queue = finished & ~chained
        # a successor of a failed cell (non-finite / locked up) restarts from its own start
        carry_on = chained & _all_finite_lanes(lane.y) & ~lane.lockup
        pos = next_job + jnp.cumsum(from_queue.astype(jnp.int32)) - 1
        head = queue[jnp.minimum(pos, queue.shape[0] - 1)]
        idx = jnp.where(chained, nxt, head)
        y_new = select_cells(carry_on, reset_accumulators(lane.y), start_state(idx))
        lane = load(lane, idx, y_new, finished)
        return lane, out, next_job + jnp.sum(from_queue.astype(jnp.int32))

    def busy(carry):
        return jnp.any(~carry[0].done)

    heads = queue[:n_lanes]
    carry = (fresh(heads, start_state(heads)), out, jnp.asarray(n_lanes))
    for smaller in pools[1:]:
        # Tail compaction: once the queue is empty and at most `smaller` cells are still
        # running, a step of this pool costs its full width for those few lanes; move them
        # into the smaller pool (a step of 8 lanes costs ~1/7 of 128 lanes', measured), so
        # the cells that need all N cycles at low frequency do not hold up the batch.
        def wide(carry, smaller=smaller):
            lane, _, next_job = carry
            queued = queue[jnp.minimum(next_job, queue.shape[0] - 1)] < n_cells
            return busy(carry) & (queued | (jnp.sum(~lane.done) > smaller))

        lane, out, next_job = jax.lax.while_loop(wide, round_, carry)
        keep = jnp.argsort(lane.done, stable=True)[:smaller]  # running lanes (idle: done)
        carry = (jax.tree_util.tree_map(lambda a: a[keep], lane), out, next_job)
    _, out, _ = jax.lax.while_loop(busy, round_, carry)
    if metrics:
        return CycleMetrics(**out)
    h = out.pop("h")
    return CycleMetrics(**out), h


@eqx.filter_jit
def _vector_field(model: ConeActuator, t, y: ConeState, args):
    """The model's vector field as one inner jit, at module level: a step evaluates it five
    times, and every pool and pass (``run_paper``'s two, a periodic stage's calls) runs its
    own step; JAX traces and lowers it once per model structure and lane shapes, and XLA
    inlines it, so the compiled step is the same (``docs/performance.md``)."""
    return model.vector_field(t, y, args)


def _all_finite_lanes(y: ConeState) -> Array:
    return jax.vmap(all_finite)(y)
