"""Warm starts across a map's grid: each cell's periodic orbit continued from its neighbour's.

The ``periodic`` protocol from rest settles every cell for up to ``warmup`` cycles and then
shoots with the full one-period Jacobian (``jacfwd`` over the d dynamical states: one shot
costs about ten periods). On a map, neighbouring payloads have nearby orbits *and* nearby
Jacobians, so :func:`neighbour_chain` solves the grid one payload-axis stage at a time:

1. the first stage (the heaviest load: its orbits are unique and settle fastest) is solved
   from rest for the block's first mass by :func:`jaxdea.engine.periodic.periodic_cells`,
   which also hands back each cell's Jacobian, and continued from mass to mass for the
   others (:func:`first_stage`);
2. every later stage starts from its neighbour's orbit, extrapolated from the last stages'
   orbits (:func:`predict`), and Jacobian and runs chord iterations
   (:mod:`jaxdea.engine.chord`): ``y <- y - (J - I)^-1 (Phi_T(y) - y)`` with ``J`` kept
   current by Broyden's rank-one update from each iteration's secant, so that each
   iteration costs one plain period instead of a shot; every column of the grid goes on at
   its own pace (:func:`chord_columns`);
3. a cell that has not converged after
   :data:`~jaxdea.engine.chord.CHORD_ITERATIONS` iterations, whose period fails, or whose
   orbit is not stable (:data:`~jaxdea.engine.periodic.STABLE_MULTIPLIER`, checked with a
   true Jacobian wherever the updated one puts the Floquet radius above
   :data:`~jaxdea.engine.chord.VERIFY_RADIUS`) is solved from rest instead, exactly as
   ``start="rest"`` would.

What is reported is the orbit continued along the chain: where responses coexist (near a
jump, lightly damped), it is the branch connected to the heavier loads, which may differ from
the orbit a run from rest falls onto. ``start="rest"`` (the default) keeps the from-rest
orbit of every cell. Measured: ``bench/full_map_slice.py`` and ``docs/models.md`` section 4.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import numpy as np

from ..models.cone import ConeActuator, ConeState, Loading
from .batch import default_lanes, schedule, scheduled_batches, take_cells
from .chord import CHORD_ITERATIONS, Chord, Iterates, chord_cells
from .lane_state import select_cells
from .metrics import CycleMetrics
from .periodic import flatten_dynamical, periodic_cells, with_dynamical
from .sharding import replicated, to_host
from .step_control import StepControl

#: Cells below this frequency (Hz) are solved from rest, in batches after the chain: they
#: settle within about 4 periods from rest anyway, and a period is so long (a 1 Hz DCDEA-LS
#: period takes ~4300 steps, a 100 Hz one ~150) that one such cell in a chord call keeps all
#: the other lanes of the call waiting. Measured on 4 masses x 50 dampings x 996
#: frequencies: the chord calls took 40 s instead of 52 s, the from-rest batches 23 s
#: instead of 12 s; about even on that grid, and the chord calls' length no longer depends
#: on the lowest frequency of the map.
REST_BELOW = 10.0
#: Orbits of the last stages a warm start extrapolates from (:func:`predict`; 5: quartic).
PREDICTOR_POINTS = 5
#: Cells per device whose stability :func:`chord_columns` checks in one shot call: a
#: converged cell with a doubtful Floquet radius waits (its column pauses) until this many
#: have gathered or nothing else is left to iterate.
VERIFY_BATCH = 32


def predict(history: np.ndarray) -> np.ndarray:
    """The next stage's start (flat dynamical states, ``(n, d)``): per cell, the polynomial
    through its orbits of the last stages, extrapolated one stage on (a map's axes are log-
    or evenly spaced, so equal steps in index are equal steps in the axis' own scale).

    Each cell uses as many of the last stages as it has (newest first, up to
    ``len(history)``; an orbit is missing, NaN, where it failed or the chain just began):
    ``y_j`` alone, the secant ``2 y_j - y_(j-1)``, then ``3 y_j - 3 y_(j-1) + y_(j-2)``, and
    so on (the k-th backward difference dropped). Measured on DCDEA-LS, drive A, 7 masses
    (every 8th of the full map's 50) x 50 dampings x 100 frequencies (every 10th of its
    0.2 Hz grid), all 35 000 cells steady in every variant: periods per cell over the whole
    map (the cells solved from rest included) 4.27 with the secant, 3.56 with three points,
    3.09 with four, 2.92 with five (:data:`PREDICTOR_POINTS`), 3.00 with six; P_out within
    9.4e-5 and P_in within 3.3e-6 of the secant's map in every variant. (Earlier, on another
    grid: 5.0 periods per chord cell with ``y_j`` alone, 4.3 with the secant.)

    **Arguments:**

    - `history`: ``(k, n, d)`` the cells' orbits of the last ``k`` stages, newest first.

    **Returns:**

    ``(n, d)`` start states.
    """
    guess = history[0]
    for p in range(2, len(history) + 1):
        coef = np.array([(-1.0) ** i * math.comb(p, i + 1) for i in range(p)])
        g = np.tensordot(coef, history[:p], axes=1)
        guess = np.where(np.isfinite(g).all(axis=1, keepdims=True), g, guess)
    return guess


def remember(history: np.ndarray, flat: np.ndarray, ok: np.ndarray,
             recent: np.ndarray) -> np.ndarray:
    """The predictor's ``history`` after a stage: ``flat`` first where the cell converged
    (``ok``), its older orbits kept only where the stage before converged too (``recent``:
    consecutive stages); where the cell failed, its last orbit stays as the seed and the
    older ones are dropped (NaN)."""
    older = np.where((ok & recent)[None, :, None], history[:-1], np.nan)
    dropped = np.concatenate([history[:1], np.full_like(history[1:], np.nan)])
    return np.where(ok[None, :, None], np.concatenate([flat[None], older]), dropped)


def stage_order(freq: np.ndarray, block: np.ndarray, n_dev: int) -> np.ndarray:
    """Slot order of one stage's columns: ``n_dev`` equal device slices, each holding an
    equal share of every block's columns (padded by repeating a column of the same block),
    lowest frequency first within a slice.

    Why per block: the first stage runs one block at a time (:func:`first_stage`), and a
    block dealt unevenly would leave a device idle (with two devices and an even number of
    blocks, plain round-robin over all columns gives each block's columns to one device).

    **Arguments:**

    - `freq`: ``(m,)`` the columns' frequencies.
    - `block`: ``(m,)`` the columns' block (mass) indices.
    - `n_dev`: the number of devices.

    **Returns:**

    Indices into the columns, a multiple of ``n_dev`` long.
    """
    parts = []
    for b in np.unique(block):
        cols = np.nonzero(block == b)[0]
        parts.append(cols[schedule(freq[cols], n_dev)].reshape(n_dev, -1))
    slots = np.concatenate(parts, axis=1)
    return np.concatenate([row[np.argsort(freq[row], kind="stable")] for row in slots])


def first_stage(actuator: ConeActuator, loadings: Loading, block: np.ndarray,
                partner: np.ndarray, *, lanes: int, **kw):
    """The chain's first stage, continued along the blocks (the map's first axis: mass).

    The first block is solved from rest (:func:`~jaxdea.engine.periodic.periodic_cells`,
    with the Jacobians of its shots); each later block starts from the orbits and
    Jacobians of the block before it at the same frequency (and phase), with the secant
    predictor (:func:`predict`), by chord iterations
    (:func:`~jaxdea.engine.chord.chord_cells`). Cells whose chord iteration fails, or that
    have no converged neighbour to start from, are solved from rest at the end, in one call.
    Every call runs on the whole stage's slots with only the block's cells active, so all
    of them share the compiled programs of the stages and batches after it.

    The first stage is the heaviest load (its orbits are unique and settle fastest), so a
    continued orbit is the from-rest one to the Newton tolerance. Measured:
    ``bench/neighbour_profile.py`` (``docs/models.md`` section 4).

    **Arguments:**

    - `actuator`, `loadings`: the stage's slots (leading axis).
    - `block`: ``(n,)`` each slot's block index.
    - `partner`: ``(n,)`` for each slot, a slot of the block before with the same frequency
      (any slot for the first block's).
    - `lanes`: lanes per device.
    - `kw`: ``tol``, ``control``, ``devices``, ``driven`` as for ``periodic_cells``.

    **Returns:**

    ``(metrics, jacobian, ok)`` per slot: host :class:`CycleMetrics`, the one-period
    Jacobians (NaN where none is known) and whether the cell converged.
    """
    blocks = np.unique(block)
    mine = block == blocks[0]
    res, jac = periodic_cells(actuator, loadings, lanes=lanes, with_jacobian=True,
                              active=mine, **kw)
    res, jac = to_host(res), np.asarray(jac)
    ok = mine & (np.asarray(res.status) == 0)
    flat = np.asarray(flatten_dynamical(res.final_state))
    history = remember(np.full((2,) + flat.shape, np.nan), flat, ok, np.zeros_like(ok))
    tried = np.zeros_like(ok)
    for b in blocks[1:]:
        mine = block == b
        behind = history[:, partner]  # the block before's orbits at the same frequency
        guess = predict(behind)
        go = mine & np.isfinite(guess).all(axis=1)
        tried |= go
        start = with_dynamical(res.final_state, np.where(go[:, None], guess, 0.0))
        r, new_jac, conv, orbit = chord_cells(actuator, loadings, start, jac[partner],
                                              lanes=lanes, active=go, **kw)
        res = to_host(select_cells(go, r, res))
        jac = np.where(go[:, None, None], new_jac, jac)
        ok = np.where(mine, go & conv, ok)
        history = np.where(mine[None, :, None],
                           remember(behind, orbit, ok, ok[partner]), history)
    late = (block != blocks[0]) & ~ok
    if late.any():  # as start="rest" would, with Jacobians for the stages after
        r, js = periodic_cells(actuator, loadings, lanes=lanes, with_jacobian=True,
                               active=late, **kw)
        r = with_spent(to_host(r), res, tried)  # and the chord's periods before
        res = to_host(select_cells(late, r, res))
        jac = np.where(late[:, None, None], np.asarray(js), jac)
        ok = np.where(late, np.asarray(r.status) == 0, ok)
    return res, jac, ok


def with_spent(metrics: CycleMetrics, before: CycleMetrics, where=None) -> CycleMetrics:
    """``metrics`` (host arrays) of a solve from rest with the steps and periods ``before``
    (another solve of the same cells, e.g. chord iterations that failed) added, in the
    cells ``where`` (default all): ``steps`` and ``cycles_run`` count all of a cell's work."""
    def total(k):
        now, spent = np.asarray(getattr(metrics, k)), np.asarray(getattr(before, k))
        return now + (spent if where is None else np.where(where, spent, 0)).astype(now.dtype)

    return eqx.tree_at(lambda m: (m.steps, m.cycles_run), metrics,
                       (total("steps"), total("cycles_run")))


def chord_columns(actuator: ConeActuator, loadings: Loading, slots: np.ndarray,
                  seed: ConeState, history: np.ndarray, jacobian: np.ndarray,
                  recent: np.ndarray, *, lanes: int, tol: float = 1e-6,
                  iterations: int = CHORD_ITERATIONS, control: StepControl = StepControl(),
                  devices: tuple = (), driven=None):
    """The chain's later stages, every column at its own pace (a generator).

    Column ``i`` (slot ``i``) holds the cells ``slots[i, j]`` of the stages ``j``; its last
    stage (``j = n_chain - 1``) is solved already. Each call of the one-period program runs
    one chord iteration (:func:`~jaxdea.engine.chord.chord_cells`) of every column that is
    not done yet, each at its own stage: a column whose iteration converged (and is
    stable) or failed goes on to its next stage at once, starting from the :func:`predict`
    of its orbits, with its Jacobian (the one it started the stage with, where the stage
    failed). So every call is as wide as the columns left, and the number of calls is set
    by the column with the most iterations over all stages, not by the sum over the stages
    of each stage's slowest cell.
    A column's iterations are the same, number for number, as stage by stage.

    **Arguments:**

    - `actuator`, `loadings`: the model and the cells (host arrays, indexed by `slots`).
    - `slots`: ``(m, n_chain)`` cell indices, ``m`` divisible by the number of `devices`.
    - `seed`: ``(m,)`` states whose non-dynamical parts every start state takes.
    - `history`: ``(k, m, d)`` each column's orbits of its last converged stages, newest
      first (:func:`remember`); updated in place.
    - `jacobian`: ``(m, d, d)`` each column's one-period Jacobian (NaN: shot first).
    - `recent`: ``(m,)`` whether the stage just solved converged.
    - `lanes`, `tol`, `iterations`, `control`, `devices`, `driven`: as for
      :func:`~jaxdea.engine.chord.chord_cells`.

    **Yields:**

    ``(where, cells, metrics, ok, jacobian)`` each time some columns finish a stage: their
    slots, the stage's cells, host :class:`CycleMetrics` (status 0 where converged, else 4),
    whether they converged, and their Broyden-updated one-period Jacobians ``(len(where),
    d, d)`` (meaningful where they converged).
    """
    chord = Chord(actuator, tuple(devices or jax.devices()[:1]), float(tol), control,
                  lanes, driven)
    m, n_chain = slots.shape
    stage = np.full(m, n_chain - 2)
    it = Iterates(predict(history), jacobian, stage >= 0)
    start_jac = it.jac.copy()
    recent = np.array(recent, bool)
    held = np.zeros(m, bool)  # converged, waiting for the shot that checks their stability
    batch = VERIFY_BATCH * len(chord.devices)
    while it.pending.any() or held.any():
        ld = take_cells(loadings, slots[np.arange(m), np.maximum(stage, 0)])
        newly, failed = np.zeros(m, bool), np.zeros(m, bool)
        if it.pending.any():
            newly, failed = chord.iterate(ld, seed, it)
            failed |= it.pending & (it.k >= int(iterations))
            it.pending &= ~failed
        doubt = chord.doubtful(it, newly)
        held |= doubt
        newly &= ~doubt
        if held.any() and (held.sum() >= batch or not it.pending.any()):
            bad = chord.unstable(ld, seed, it, held)
            newly, failed = newly | (held & ~bad), failed | (held & bad)
            held[:] = False
        it.converged |= newly
        done = newly | failed
        if not done.any():
            continue
        where = np.nonzero(done)[0]
        metrics, ok = it.metrics(where), it.converged[where]
        yield where, slots[where, stage[where]], metrics, ok, it.jac[where]
        history[:, where] = remember(history[:, where], it.orbit[where], ok, recent[where])
        recent[where] = ok
        it.jac[where] = np.where(ok[:, None, None], it.jac[where], start_jac[where])
        stage[where] -= 1
        go = where[stage[where] >= 0]
        if go.size:  # the next stage of these columns
            again = np.zeros(m, bool)
            again[go] = True
            guess = it.flat.copy()
            guess[go] = predict(history[:, go])
            it.restart(again, guess)
            start_jac[go] = it.jac[go]


def _scatter(results, cells, res):
    """Write the per-slot results ``res`` (host arrays) into ``results`` at ``cells``."""
    jax.tree_util.tree_map(lambda dst, src: dst.__setitem__(cells, np.asarray(src)),
                           results, res)


def _blank(like, n: int):
    """Zeroed host arrays for ``n`` cells shaped like the per-cell results ``like``."""
    return jax.tree_util.tree_map(
        lambda a: np.zeros((n,) + np.shape(a)[1:], np.asarray(a).dtype), like)


def chain_layout(freq: np.ndarray, shape: tuple[int, int, int],
                 n_dev: int) -> tuple[np.ndarray, np.ndarray]:
    """The chain's columns over a block of cells in C order ``shape = (blocks, n_chain,
    rest)`` with frequencies ``freq``, and their slot order on ``n_dev`` devices.

    Returns ``(columns, order)``: ``columns[i, j]`` is the cell of column ``i`` at stage
    ``j`` (a column per cell of stage 0 at or above :data:`REST_BELOW`; the other cells are
    solved from rest), and ``order`` the columns' slots (:func:`stage_order`: its length
    is the size of every stage's calls)."""
    blocks, n_chain, rest = (int(k) for k in shape)
    first = np.arange(blocks * n_chain * rest).reshape(blocks, n_chain, rest)[:, 0, :].ravel()
    chained = first[freq[first] >= REST_BELOW]  # stage 0's cells at or above REST_BELOW
    columns = chained[:, None] + rest * np.arange(n_chain)  # (column, stage) -> cell
    block = chained // (n_chain * rest)  # each column's block (mass)
    order = stage_order(freq[chained], block, n_dev) if chained.size else np.zeros(0, int)
    return columns, order


def neighbour_chain(actuator: ConeActuator, loadings: Loading, shape: tuple[int, int, int], *,
                    tol: float = 1e-6, control: StepControl = StepControl(),
                    devices: tuple | None = None, driven=None, with_jacobian: bool = False):
    """Periodic steady state of a block of map cells, each warm-started from its neighbour.

    **Arguments:**

    - `actuator`: the cone model.
    - `loadings`: cells in C order ``shape = (blocks, n_chain, rest)``: for a map chunk of
      whole masses, ``(M, c, f x phase)``. The chain runs along the middle axis, from its
      last index (the heaviest load) down; each stage holds ``blocks x rest`` cells.
    - `tol`, `control`: as for :func:`~jaxdea.engine.periodic.periodic_cells`.
    - `devices`: JAX devices to split each stage's cells over (dealt lowest frequency first,
      :func:`~jaxdea.engine.batch.schedule`); default the first device.
    - `driven`: the driven membranes (default all).
    - `with_jacobian`: also return each cell's one-period Jacobian at its orbit.

    **Returns:**

    :class:`CycleMetrics` per cell, in the cells' order (host arrays). ``cycles_run`` and
    ``steps`` count the primal periods and steps a cell took (chord iterations, and its
    solve from rest where it fell back). With `with_jacobian`, ``(metrics, jacobian)``:
    ``(n, d, d)`` float32, the Jacobian each chained cell converged with (its shot's in the
    first stage, Broyden-updated in the later ones; NaN for the cells solved from rest),
    for :func:`~jaxdea.engine.coexist.coexisting` to start its chord iterations from.

    A cell whose chord iteration fails is solved from rest after the chain, together with
    the others of the block that failed (one batch keeps the lanes busy), and the chain goes
    on past it from the last orbit that converged in its column.
    """
    devices = tuple(devices or jax.devices()[:1])
    n_dev = len(devices)
    loadings = to_host(loadings)  # host arrays: every stage gathers its cells from them
    actuator = replicated(actuator, devices)  # on every device once, not once per call
    blocks, n_chain, rest = (int(k) for k in shape)
    n = blocks * n_chain * rest
    freq = np.asarray(loadings.drive.frequency)
    columns, order = chain_layout(freq, (blocks, n_chain, rest), n_dev)
    chained = columns[:, 0]
    rest_cells = np.setdiff1d(np.arange(n), columns.ravel())
    block = chained // (n_chain * rest)  # each column's block (mass)
    keep = np.unique(order, return_index=True)[1]  # one slot per cell (padding repeats one)
    # each slot's neighbour in the block before (same frequency and phase), for the first
    # stage's continuation along the blocks
    slot_of = np.empty(chained.size, int)
    slot_of[order[keep]] = keep
    below = np.searchsorted(chained, chained[order] - n_chain * rest)
    partner = np.where(block[order] > 0, slot_of[np.minimum(below, chained.size - 1)],
                       np.arange(order.size))
    lanes = default_lanes(order.size // n_dev, devices) if order.size else None
    kw = dict(tol=float(tol), control=control, devices=devices, driven=driven)
    results, failed, jacobians = None, [rest_cells], None
    if chained.size:
        slots = columns[order]  # (slot, stage) -> cell
        first = n_chain - 1
        res, jac, ok = first_stage(actuator, take_cells(loadings, slots[:, first]),
                                   block[order], partner, lanes=lanes, **kw)
        results = _blank(res, n)
        _scatter(results, slots[keep, first], take_cells(res, keep))
        failed.append(slots[keep, first][~ok[keep]])
        # each column's seeds for the predictor: its orbits of consecutive converged stages
        flat = np.asarray(flatten_dynamical(res.final_state))
        history = remember(np.full((PREDICTOR_POINTS,) + flat.shape, np.nan), flat, ok,
                           np.zeros_like(ok))
        jac = np.where(ok[:, None, None], jac, np.nan)
        if with_jacobian:
            jacobians = np.full((n,) + jac.shape[1:], np.nan, np.float32)
            jacobians[slots[keep, first]] = jac[keep]
        is_kept = np.zeros(order.size, bool)
        is_kept[keep] = True
        for where, cells, res, ok, js in chord_columns(actuator, loadings, slots,
                                                       res.final_state, history, jac, ok,
                                                       lanes=lanes, **kw):
            mine = is_kept[where]
            _scatter(results, cells[mine], take_cells(res, np.nonzero(mine)[0]))
            failed.append(cells[mine & ~ok])
            if with_jacobian:
                jacobians[cells[mine & ok]] = js[mine & ok]
    failed = np.concatenate(failed)
    # the stage's own shape (its programs are compiled already), or without a chain all cells
    size = order.size or -(-n // n_dev) * n_dev
    # solved from rest, as start="rest" would be
    for sub, real in scheduled_batches(failed, size, freq, n_dev):
        back = to_host(periodic_cells(actuator, take_cells(loadings, sub), active=real,
                                      lanes=lanes or default_lanes(size // n_dev, devices), **kw))
        results = _blank(back, n) if results is None else results
        back = with_spent(back, take_cells(results, sub))
        _scatter(results, sub[real], take_cells(back, real))
    if not with_jacobian:
        return results
    if jacobians is None:  # no chain: every cell from rest
        d = np.asarray(flatten_dynamical(results.final_state)).shape[-1]
        jacobians = np.full((n, d, d), np.nan, np.float32)
    return results, jacobians
