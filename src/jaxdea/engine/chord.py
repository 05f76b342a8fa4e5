"""Chord iterations for periodic orbits: Newton's method on the one-period map with the
Jacobian kept current by Broyden's rank-one update, so that an iteration costs one plain
period instead of a shot (``jacfwd`` over the d dynamical states: about ten periods).

Used by :mod:`jaxdea.engine.warmstart`, which starts each cell from its neighbour's orbit
and Jacobian: ``y <- y - (J - I)^-1 (Phi_T(y) - y)``, converged when the Newton step (scaled,
:func:`~jaxdea.engine.periodic.step_residual`) is below ``tol``; a converged orbit whose
updated Jacobian puts the Floquet radius above :data:`VERIFY_RADIUS` is checked by one true
shot and kept only if no multiplier is above
:data:`~jaxdea.engine.periodic.STABLE_MULTIPLIER`.
"""

from __future__ import annotations

import jax
import numpy as np

from ..models.cone import ConeActuator, ConeState, Loading
from .metrics import CycleMetrics
from .periodic import (
    PER_CELL,
    STABLE_MULTIPLIER,
    flatten_dynamical,
    newton_step,
    one_period,
    radius_above,
    settle_pools,
    settle_program,
    shoot_period,
    shooting_lanes,
    step_residual,
    with_dynamical,
)
from .sharding import cell_sharded, to_host
from .step_control import StepControl

#: Chord iterations (one period each) before a warm-started cell is solved from rest. On the
#: DCDEA-LS bench grid (2 masses x 50 dampings x 100 frequencies) a warm-started cell took
#: 5.2 periods on average; 2 % needed more than 8.
CHORD_ITERATIONS = 8
#: Floquet radius of the Broyden-updated Jacobian above which a chord-converged orbit's
#: stability is checked with a true Jacobian (one shot).
VERIFY_RADIUS = 0.98


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

    ``(metrics, jacobian, converged, orbits)``: :class:`CycleMetrics` of the last period
    from each cell's final iterate, the updated Jacobians, a bool per cell, true where the
    chord iteration converged to a stable orbit (elsewhere the metrics are meaningless), and
    each cell's best estimate of its orbit (``(n, d)``, :attr:`Iterates.orbit`: the seed a
    neighbour's warm start extrapolates from).
    """
    chord = Chord(actuator, tuple(devices or jax.devices()[:1]), float(tol), control,
                  lanes, driven)
    seed = to_host(initial)
    flat = np.asarray(flatten_dynamical(seed))
    it = Iterates(flat, jacobian, np.ones(flat.shape[0], bool) if active is None else active)
    for _ in range(int(iterations)):
        newly, _ = chord.iterate(loadings, seed, it)
        it.converged |= newly
        if not it.pending.any():
            break
    it.converged &= ~chord.unstable(loadings, seed, it, chord.doubtful(it, it.converged))
    return it.metrics(), it.jac, it.converged, it.orbit


class Iterates:
    """The chord iteration's state per cell (host arrays): the iterate ``flat``, the
    Jacobian ``jac``, the last iterate and its gap (Broyden's secant; NaN before the first),
    which cells are still ``pending`` and which ``converged``, the iterations done ``k``, the
    metrics ``out`` of each cell's last period and its ``steps`` and ``cycles`` so far.

    ``orbit`` is each cell's best estimate of its periodic orbit: its last iterate with that
    iteration's Newton step taken (the end of its last period where no step was computed;
    NaN before its first period). The metrics are those of the period from the iterate
    itself, whose distance to the orbit the step measures; the stepped iterate is closer
    still (by a factor of the chord's contraction), so a neighbour's warm start extrapolates
    from it (:func:`jaxdea.engine.warmstart.predict`). Measured: extrapolating from the
    period's end instead amplifies its ~tol error by the predictor's weights (5 points:
    up to 31x)."""

    def __init__(self, flat, jacobian, pending):
        n = np.shape(flat)[0]
        self.flat = np.array(flat, dtype=float)
        self.jac = np.array(jacobian, dtype=float)
        self.pending = np.array(pending, bool)
        self.prev = (np.full_like(flat, np.nan), np.full_like(flat, np.nan))
        self.converged = np.zeros(n, bool)
        self.k = np.zeros(n, np.int64)
        self.out = None
        self.orbit = np.full_like(self.flat, np.nan)
        self.steps, self.cycles = np.zeros(n, np.int64), np.zeros(n, np.int64)

    def restart(self, where, flat):
        """Start a new chord iteration in the cells ``where`` from ``flat``."""
        self.flat = np.where(where[:, None], flat, self.flat)
        self.orbit = np.where(where[:, None], np.nan, self.orbit)
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


class Chord:
    """One chord iteration of many cells at a time: the compiled programs and settings."""

    def __init__(self, actuator, devices, tol, control, lanes, driven):
        self.actuator, self.tol = actuator, tol
        self.control, self.lanes, self.driven = control, lanes, driven
        self.shot_kw = dict(control=control, lanes=shooting_lanes(lanes, devices),
                            driven=driven)
        self.devices = devices
        # a period is the settling program with a budget of one period (one_period): the
        # program the chain's from-rest solves compiled already, ending in the same narrow
        # pool as they do, so that a call with a few cells left costs a few lanes' steps
        self.one = settle_program(devices)
        self.shoot = cell_sharded(shoot_period, devices)

    def iterate(self, loadings, seed, it: Iterates):
        """One period of every pending cell of ``it`` (a shot where its Jacobian is not
        finite yet, at its first iteration), Broyden's update of its Jacobian and the Newton
        step. Updates ``it`` in place (``converged`` excepted).

        Returns ``(newly, failed)``: the cells that converged in this iteration (stability
        not checked yet: :meth:`doubtful`, :meth:`unstable`), and those whose iteration
        stopped without (a failed period or a non-finite step)."""
        pending = it.pending
        y = with_dynamical(seed, it.flat)
        fresh = pending & (it.k == 0) & ~np.isfinite(it.jac).all(axis=(1, 2))
        n_local = jax.tree_util.tree_leaves(loadings)[0].shape[0] // len(self.devices)
        r = one_period(self.one, self.actuator, loadings, y, pending & ~fresh,
                       control=self.control, pools=settle_pools(n_local, self.lanes),
                       driven=self.driven)
        if fresh.any():  # shot first: exact Jacobians
            rs, js, _ = to_host(self.shoot(self.actuator, loadings, y, fresh, **self.shot_kw))
            r = pick(fresh, rs, r)
            it.jac = np.where(fresh[:, None, None], np.asarray(js), it.jac)
        flat = it.flat
        gap = np.asarray(flatten_dynamical(r.final_state)) - flat
        it.out = r if it.out is None else pick(pending, r, it.out)
        it.steps += np.where(pending, np.asarray(r.steps), 0)
        it.cycles += np.where(pending, np.asarray(r.cycles_run), 0)
        secant = np.flatnonzero(pending & np.isfinite(it.prev[0]).all(axis=1))
        if secant.size:  # Broyden's update of J - I from the secant of this iteration
            dx, dg = flat[secant] - it.prev[0][secant], gap[secant] - it.prev[1][secant]
            jac = it.jac[secant]
            with np.errstate(invalid="ignore"):
                miss = dg - np.einsum("nij,nj->ni", jac - np.eye(jac.shape[-1]), dx)
                upd = miss[:, :, None] * dx[:, None, :] / np.maximum(
                    np.einsum("ni,ni->n", dx, dx), 1e-300)[:, None, None]
            it.jac = it.jac.copy()
            it.jac[secant] = jac + upd
        ok = np.asarray(r.status) == 0
        step = newton_step(it.jac, gap, pending & ok)
        size = np.asarray(step_residual(y, step))
        newly = pending & ok & (size < self.tol)
        stepped = pending & ok & np.isfinite(step).all(axis=1)
        it.pending = stepped & ~newly
        it.prev = (flat, gap)
        it.orbit = np.where(stepped[:, None], flat + step,
                            np.where(pending[:, None], flat + gap, it.orbit))
        it.flat = flat + np.where(it.pending[:, None], step, 0.0)
        it.k = it.k + pending
        return newly, pending & ~it.pending & ~newly

    def doubtful(self, it: Iterates, where):
        """Which of the converged cells ``where`` need a shot to show that they are stable:
        those whose updated Jacobian puts the Floquet radius above :data:`VERIFY_RADIUS`."""
        doubt = where.copy()
        doubt[where] = radius_above(it.jac[where], VERIFY_RADIUS)
        return doubt

    def unstable(self, loadings, seed, it: Iterates, doubt):
        """Which of the :meth:`doubtful` cells ``doubt`` are not stable: one shot each, whose
        true Jacobian replaces the updated one, with a multiplier above
        :data:`~jaxdea.engine.periodic.STABLE_MULTIPLIER`."""
        if not doubt.any():
            return np.zeros_like(doubt)
        _, js, _ = to_host(self.shoot(self.actuator, loadings,
                                      with_dynamical(seed, it.flat), doubt,
                                      **self.shot_kw))
        it.jac = np.where(doubt[:, None, None], np.asarray(js), it.jac)
        bad = doubt.copy()
        bad[doubt] = radius_above(it.jac[doubt], STABLE_MULTIPLIER)
        return bad


def pick(mask, a, b):
    """Per cell, ``a``'s leaves where ``mask`` else ``b``'s (host arrays, numpy)."""
    return jax.tree_util.tree_map(
        lambda x, y: np.where(mask.reshape(mask.shape + (1,) * (np.ndim(x) - 1)), x, y), a, b)
