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
   orbits (:func:`predict`), and Jacobian and runs chord iterations (:func:`chord_cells`):
   ``y <- y - (J - I)^-1 (Phi_T(y) - y)`` with ``J`` kept current by Broyden's rank-one
   update from each iteration's secant, so that each iteration costs one plain period
   instead of a shot;
3. a cell that has not converged after :data:`CHORD_ITERATIONS` iterations, whose period
   fails, or whose orbit is not stable (:data:`~jaxdea.engine.periodic.STABLE_MULTIPLIER`,
   checked with a true Jacobian wherever the updated one puts the Floquet radius above
   :data:`VERIFY_RADIUS`) is solved from rest instead, exactly as ``start="rest"`` would.

What is reported is the orbit continued along the chain: where responses coexist (near a
jump, lightly damped), it is the branch connected to the heavier loads, which may differ from
the orbit a run from rest falls onto. ``start="rest"`` (the default) keeps the from-rest
orbit of every cell. Measured: ``bench/full_map_slice.py`` and ``docs/models.md`` section 4.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.cone import ConeActuator, ConeState, Loading
from .batch import default_lanes, schedule, take_cells
from .lanes import run_protocol, select_cells
from .metrics import CycleMetrics
from .periodic import (
    PER_CELL,
    SHOOTING_LANES,
    STABLE_MULTIPLIER,
    flatten_dynamical,
    floquet_radius,
    newton_step,
    periodic_cells,
    shoot_period,
    step_residual,
    with_dynamical,
)
from .sharding import cell_sharded, to_host
from .step_control import StepControl

#: Chord iterations (one period each) before a warm-started cell is solved from rest. On the
#: DCDEA-LS bench grid (2 masses x 50 dampings x 100 frequencies) a warm-started cell took
#: 5.2 periods on average; 2 % needed more than 8.
CHORD_ITERATIONS = 8
#: Cells below this frequency (Hz) are solved from rest, in batches after the chain: they
#: settle within about 4 periods from rest anyway, and a period is so long (a 1 Hz DCDEA-LS
#: period takes ~4300 steps, a 100 Hz one ~150) that one such cell in a chord call keeps all
#: the other lanes of the call waiting. Measured on 4 masses x 50 dampings x 996
#: frequencies: the chord calls took 40 s instead of 52 s, the from-rest batches 23 s
#: instead of 12 s; about even on that grid, and the chord calls' length no longer depends
#: on the lowest frequency of the map.
REST_BELOW = 10.0
#: Narrower lane pools a chord call's period ends in (:func:`jaxdea.engine.lanes.lane_pools`).
#: A call lasts as long as its longest period, and after the first iterations only a few
#: cells of a stage are still pending: in a 128-lane pool each of their steps costs the
#: full width. One period of an 11-200 Hz stage (2400 cells, 2 devices), after compile:
#: 20 cells active 47 -> 10.6 ms with a 32-lane tail (16 lanes: 12.5), 200 cells 40.7 ->
#: 19.7 ms, all 2400 98 -> 66 ms.
CHORD_TAIL_POOLS = (32,)
#: Orbits of the last stages a warm start extrapolates from (:func:`predict`; 5: quartic).
PREDICTOR_POINTS = 5
#: Cells per device whose stability :func:`chord_columns` checks in one shot call: a
#: converged cell with a doubtful Floquet radius waits (its column pauses) until this many
#: have gathered or nothing else is left to iterate.
VERIFY_BATCH = 32
#: Floquet radius of the Broyden-updated Jacobian above which a chord-converged orbit's
#: stability is checked with a true Jacobian (one shot).
VERIFY_RADIUS = 0.98


def _one_period(actuator, loadings, initial, active, *, control, lanes, driven):
    return run_protocol(actuator, loadings, cycles=1, average=1, initial=initial,
                        active=active, control=control,
                        pools=tuple(p for p in (lanes,) + CHORD_TAIL_POOLS if p <= lanes),
                        driven=driven)


def chord_cells(actuator: ConeActuator, loadings: Loading, initial: ConeState,
                jacobian: np.ndarray, *, tol: float = 1e-6,
                iterations: int = CHORD_ITERATIONS, control: StepControl = StepControl(),
                lanes: int = 128, devices: tuple = (), driven=None, active=None):
    """Periodic orbits by chord iterations with Broyden-updated Jacobians, from given states.

    **Arguments:**

    - `actuator`, `loadings`: the cells (leading axis), their number divisible by the number
      of `devices`.
    - `initial`: start state of every cell (a neighbour's orbit).
    - `jacobian`: ``(n, d, d)`` one-period Jacobians to start from (a neighbour's); a cell
      whose Jacobian is not finite gets a true one by one shot first.
    - `tol`: the Newton step size (scaled, :func:`~jaxdea.engine.periodic.step_residual`)
      below which a cell has converged, as in ``periodic_cells``.
    - `iterations`: most chord iterations.
    - `control`, `lanes`, `devices`, `driven`: as for ``periodic_cells``.
    - `active`: bool per cell, iterate only these (the others are skipped at no cost and
      come back not converged); default all.

    **Returns:**

    ``(metrics, jacobian, converged)``: :class:`CycleMetrics` of the last period from each
    cell's final iterate, the updated Jacobians, and a bool per cell, true where the chord
    iteration converged to a stable orbit (elsewhere the metrics are meaningless).
    """
    chord = _Chord(actuator, tuple(devices or jax.devices()[:1]), float(tol), control,
                   lanes, driven)
    seed = to_host(initial)
    n = np.asarray(flatten_dynamical(seed)).shape[0]
    it = _Iterates.begin(np.asarray(flatten_dynamical(seed)), jacobian,
                         np.ones(n, bool) if active is None else np.array(active, bool))
    for _ in range(int(iterations)):
        newly, _ = chord.iterate(loadings, seed, it)
        it.converged |= newly
        if not it.pending.any():
            break
    if it.converged.any():
        it.converged &= ~chord.unstable(loadings, seed, it, it.converged)
    return it.metrics(), it.jac, it.converged


class _Iterates:
    """The chord iteration's state per cell (host arrays): the iterate ``flat``, the
    Jacobian ``jac``, the last iterate and its gap (Broyden's secant; NaN before the first),
    which cells are still ``pending`` and which ``converged``, the iterations done ``k``, the
    metrics ``out`` of each cell's last period and its ``steps`` and ``cycles`` so far."""

    def __init__(self, flat, jac, pending):
        n = flat.shape[0]
        self.flat, self.jac, self.pending = flat, jac, pending
        self.prev = (np.full_like(flat, np.nan), np.full_like(flat, np.nan))
        self.converged = np.zeros(n, bool)
        self.k = np.zeros(n, np.int64)
        self.out = None
        self.steps, self.cycles = np.zeros(n, np.int64), np.zeros(n, np.int64)

    @classmethod
    def begin(cls, flat, jacobian, pending):
        return cls(np.array(flat, dtype=float), np.array(jacobian, dtype=float),
                   np.array(pending, bool))

    def restart(self, where, flat):
        """Start a new chord iteration in the cells ``where`` from ``flat``."""
        self.flat = np.where(where[:, None], flat, self.flat)
        self.prev = tuple(np.where(where[:, None], np.nan, a) for a in self.prev)
        self.pending |= where
        self.converged &= ~where
        for name in ("k", "steps", "cycles"):
            setattr(self, name, np.where(where, 0, getattr(self, name)))

    def metrics(self, where=slice(None)) -> CycleMetrics:
        """:class:`CycleMetrics` (host) of the cells ``where``: their last period, the
        steps and periods of the whole iteration, status 0 where converged else 4."""
        fields = {k: np.asarray(getattr(self.out, k))[where] for k in PER_CELL}
        fields.update(steps=self.steps[where].astype(fields["steps"].dtype),
                      cycles_run=self.cycles[where].astype(fields["cycles_run"].dtype),
                      status=np.where(self.converged[where], 0, 4).astype(
                          fields["status"].dtype))
        final = jax.tree_util.tree_map(lambda a: np.asarray(a)[where], self.out.final_state)
        return CycleMetrics(final_state=final, **fields)


class _Chord:
    """One chord iteration of many cells at a time: the compiled programs and settings."""

    def __init__(self, actuator, devices, tol, control, lanes, driven):
        self.actuator, self.tol = actuator, tol
        self.kw = dict(control=control, lanes=lanes, driven=driven)
        self.shot_kw = dict(control=control, lanes=min(lanes, SHOOTING_LANES), driven=driven)
        self.devices = devices
        self.one = cell_sharded(_one_period, devices)
        self.shoot = cell_sharded(shoot_period, devices)

    def iterate(self, loadings, seed, it: _Iterates):
        """One period of every pending cell of ``it`` (a shot where its Jacobian is not
        finite yet, at its first iteration), Broyden's update of its Jacobian and the Newton
        step. Updates ``it`` in place (``converged`` excepted).

        Returns ``(newly, failed)``: the cells that converged in this iteration (stability
        not checked yet: :meth:`unstable`), and those whose iteration stopped without (a
        failed period or a non-finite step)."""
        pending = it.pending
        y = with_dynamical(seed, jnp.asarray(it.flat))
        fresh = pending & (it.k == 0) & ~np.isfinite(it.jac).all(axis=(1, 2))
        r = to_host(self.one(self.actuator, loadings, y, pending & ~fresh, **self.kw))
        if fresh.any():  # shot first: exact Jacobians
            rs, js, _ = to_host(self.shoot(self.actuator, loadings, y, fresh, **self.shot_kw))
            r = _pick(fresh, rs, r)
            it.jac = np.where(fresh[:, None, None], np.asarray(js), it.jac)
        flat = it.flat
        gap = np.asarray(flatten_dynamical(r.final_state)) - flat
        it.out = r if it.out is None else _pick(pending, r, it.out)
        it.steps += np.where(pending, np.asarray(r.steps), 0)
        it.cycles += np.where(pending, np.asarray(r.cycles_run), 0)
        secant = pending & np.isfinite(it.prev[0]).all(axis=1)
        if secant.any():  # Broyden's update of J - I from the secant of this iteration
            dx, dg = flat - it.prev[0], gap - it.prev[1]
            with np.errstate(invalid="ignore"):
                miss = dg - np.einsum("nij,nj->ni", it.jac - np.eye(it.jac.shape[-1]), dx)
                upd = miss[:, :, None] * dx[:, None, :] / np.maximum(
                    np.einsum("ni,ni->n", dx, dx), 1e-300)[:, None, None]
            it.jac = np.where(secant[:, None, None], it.jac + upd, it.jac)
        ok = np.asarray(r.status) == 0
        step = newton_step(it.jac, gap, pending & ok)
        size = np.asarray(step_residual(y, step))
        newly = pending & ok & (size < self.tol)
        it.pending = pending & ok & ~newly & np.isfinite(step).all(axis=1)
        it.prev = (flat, gap)
        it.flat = flat + np.where(it.pending[:, None], step, 0.0)
        it.k = it.k + pending
        return newly, pending & ~it.pending & ~newly

    def unstable(self, loadings, seed, it: _Iterates, where):
        """Which of the converged cells ``where`` are not stable: the updated Jacobian's
        Floquet radius, checked by one shot (which replaces the Jacobian) where it is above
        :data:`VERIFY_RADIUS`."""
        doubt = where.copy()
        doubt[where] = ~(floquet_radius(it.jac[where]) <= VERIFY_RADIUS)
        if not doubt.any():
            return np.zeros_like(where)
        _, js, _ = to_host(self.shoot(self.actuator, loadings,
                                      with_dynamical(seed, jnp.asarray(it.flat)), doubt,
                                      **self.shot_kw))
        it.jac = np.where(doubt[:, None, None], np.asarray(js), it.jac)
        bad = doubt.copy()
        bad[doubt] = ~(floquet_radius(it.jac[doubt]) <= STABLE_MULTIPLIER)
        return bad


def _pick(mask, a, b):
    """Per cell, ``a``'s leaves where ``mask`` else ``b``'s (host arrays, numpy)."""
    return jax.tree_util.tree_map(
        lambda x, y: np.where(mask.reshape(mask.shape + (1,) * (np.ndim(x) - 1)), x, y), a, b)


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
    predictor (:func:`predict`), by chord iterations (:func:`chord_cells`). Cells whose
    chord iteration fails, or that have no converged neighbour to start from, are solved
    from rest at the end, in one call. Every call runs on the whole stage's slots with only
    the block's cells active, so all of them share the compiled programs of the stages and
    batches after it.

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
        start = to_host(with_dynamical(res.final_state, jnp.asarray(
            np.where(go[:, None], guess, 0.0))))
        r, new_jac, conv = chord_cells(actuator, loadings, start, jac[partner], lanes=lanes,
                                       active=go, **kw)
        res = to_host(select_cells(go, r, res))
        jac = np.where(go[:, None, None], new_jac, jac)
        ok = np.where(mine, go & conv, ok)
        flat = np.asarray(flatten_dynamical(r.final_state))
        history = np.where(mine[None, :, None],
                           remember(behind, flat, ok, ok[partner]), history)
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
    one chord iteration (:func:`chord_cells`) of every column that is not done yet, each at
    its own stage: a column whose iteration converged (and is stable) or failed goes on to
    its next stage at once, starting from the :func:`predict` of its orbits, with its
    Jacobian (the one it started the stage with, where the stage failed). So every call is
    as wide as the columns left, and the number of calls is set by the column with the most
    iterations over all stages, not by the sum over the stages of each stage's slowest cell.
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
      :func:`chord_cells`.

    **Yields:**

    ``(where, cells, metrics, ok)`` each time some columns finish a stage: their slots, the
    stage's cells, host :class:`CycleMetrics` (status 0 where converged, else 4) and whether
    they converged.
    """
    chord = _Chord(actuator, tuple(devices or jax.devices()[:1]), float(tol), control,
                   lanes, driven)
    m, n_chain = slots.shape
    stage = np.full(m, n_chain - 2)
    it = _Iterates.begin(predict(history), jacobian, stage >= 0)
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
        doubt = newly.copy()
        doubt[newly] = ~(floquet_radius(it.jac[newly]) <= VERIFY_RADIUS)
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
        yield where, slots[where, stage[where]], metrics, ok
        flat = np.asarray(flatten_dynamical(it.out.final_state))[where]  # one shape: compiled once
        history[:, where] = remember(history[:, where], flat, ok, recent[where])
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


def neighbour_chain(actuator: ConeActuator, loadings: Loading, shape: tuple[int, int, int], *,
                    tol: float = 1e-6, control: StepControl = StepControl(),
                    devices: tuple | None = None, driven=None) -> CycleMetrics:
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

    **Returns:**

    :class:`CycleMetrics` per cell, in the cells' order (host arrays). ``cycles_run`` and
    ``steps`` count the primal periods and steps a cell took (chord iterations, and its
    solve from rest where it fell back).

    A cell whose chord iteration fails is solved from rest after the chain, together with
    the others of the block that failed (one batch keeps the lanes busy), and the chain goes
    on past it from the last orbit that converged in its column.
    """
    devices = tuple(devices or jax.devices()[:1])
    n_dev = len(devices)
    loadings = to_host(loadings)  # host arrays: every stage gathers its cells from them
    blocks, n_chain, rest = (int(k) for k in shape)
    n = blocks * n_chain * rest
    idx = np.arange(n).reshape(blocks, n_chain, rest)
    freq = np.asarray(loadings.drive.frequency)
    first = idx[:, 0, :].ravel()
    chained = first[freq[first] >= REST_BELOW]  # stage 0's cells at or above REST_BELOW
    columns = chained[:, None] + rest * np.arange(n_chain)  # (column, stage) -> cell
    rest_cells = np.setdiff1d(np.arange(n), columns.ravel())
    block = chained // (n_chain * rest)  # each column's block (mass)
    order = stage_order(freq[chained], block, n_dev) if chained.size else np.zeros(0, int)
    keep = np.unique(order, return_index=True)[1]  # one slot per cell (padding repeats one)
    # each slot's neighbour in the block before (same frequency and phase), for the first
    # stage's continuation along the blocks
    slot_of = np.empty(chained.size, int)
    slot_of[order[keep]] = keep
    below = np.searchsorted(chained, chained[order] - n_chain * rest)
    partner = np.where(block[order] > 0, slot_of[np.minimum(below, chained.size - 1)],
                       np.arange(order.size))
    lanes = default_lanes(order.size // n_dev) if order.size else None
    kw = dict(tol=float(tol), control=control, devices=devices, driven=driven)
    results, failed = None, [rest_cells]
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
        is_kept = np.zeros(order.size, bool)
        is_kept[keep] = True
        for where, cells, res, ok in chord_columns(actuator, loadings, slots, res.final_state,
                                                   history, jac, ok, lanes=lanes, **kw):
            mine = is_kept[where]
            _scatter(results, cells[mine], take_cells(res, np.nonzero(mine)[0]))
            failed.append(cells[mine & ~ok])
    failed = np.concatenate(failed)
    # the stage's own shape (its programs are compiled already), or without a chain all cells
    size = order.size or -(-n // n_dev) * n_dev
    for lo in range(0, failed.size, size):  # solved from rest, as start="rest" would be
        part = failed[lo:lo + size]
        padded = np.concatenate([part, np.full(size - part.size, part[-1])])
        sub = padded[schedule(freq[padded], n_dev)]
        real = np.zeros(size, bool)  # the padding slots are skipped at no cost
        real[np.unique(sub, return_index=True)[1]] = True
        back = to_host(periodic_cells(actuator, take_cells(loadings, sub), active=real,
                                      lanes=lanes or default_lanes(size // n_dev), **kw))
        results = _blank(back, n) if results is None else results
        back = with_spent(back, take_cells(results, sub))
        _scatter(results, sub[real], take_cells(back, real))
    return results
