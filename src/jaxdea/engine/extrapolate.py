"""Extrapolation of a cell's slow transient: the state after many more cycles, from the last few.

Why: in the papers' protocol (N cycles from rest, the last k averaged) a lightly damped cell
at a high frequency decays by only a few per cent per cycle, so it runs 60-100 of its cycles
before its early exit fires or its budget ends, although after ~20 cycles its transient is
already a sum of a few geometric modes. Then the cycle-start states ``x_j`` (the one-period
map's iterates) obey a linear recurrence of low order ``m`` in their differences
``d_j = x_{j+1} - x_j``::

    d_{j+m} = c_0 d_j + c_1 d_{j+1} + ... + c_{m-1} d_{j+m-1}

(the minimal polynomial of the period map's slowest Floquet multipliers, complex pairs
included), and the state after cycle ``N - k`` is ``x_n`` plus the recurrence's differences
summed forward. The lane engine (:func:`jaxdea.engine.lanes.run_protocol`, ``StepControl(
extrapolate=...)``) jumps there, then integrates the averaged cycles as usual.

The recurrence is fitted by least squares on the last ``2m`` difference equations (scaled
states, :data:`~jaxdea.engine.step_control.SCALES`); a second fit without the newest
difference predicts it, and that prediction's relative error times the size of the jump
(times ``1 + size / |d_n|``, :func:`predict`) is the jump's error estimate. A jump is taken
only when that estimate is below the tolerance and the predicted differences decay.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..models.cone import ConeState
from .metrics import DYNAMICAL
from .step_control import SCALES

#: Order of the fitted recurrence (modes of the transient); measured on 64 DCDEA-LS cells at
#: 60-200 Hz (``bench/NOTES.md``): order 2 and 3 left 1e-2 errors where 4 reached the
#: integration's own noise.
ORDER = 4
#: Cycle-start states kept per lane: the ``3 m + 1`` of the fit and one more for the check.
HISTORY = 3 * ORDER + 2


def flatten(y: ConeState) -> Array:
    """The dynamical states of one cell as one vector, each divided by its absolute scale."""
    return jnp.concatenate([jnp.ravel(getattr(y, k)) / SCALES[k][0] for k in DYNAMICAL])


def unflatten(x: Array, like: ConeState) -> ConeState:
    """``like`` with its dynamical states from a :func:`flatten` vector."""
    parts, i = {}, 0
    for k in DYNAMICAL:
        a = getattr(like, k)
        parts[k] = (x[i:i + a.size] * SCALES[k][0]).reshape(a.shape).astype(a.dtype)
        i += a.size
    return ConeState(**{**{k: getattr(like, k) for k in ("payload_work", "v2", "energy_in")},
                        **parts})


def _solve_spd(g: Array, r: Array) -> Array:
    """``g^-1 r`` for a small symmetric positive definite ``g`` (Cholesky, unrolled: no
    LAPACK call, which a sharded CPU program must not make, ``tests/test_no_collectives``)."""
    m = g.shape[0]
    ell = [[None] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            s = g[i, j] - sum(ell[i][k] * ell[j][k] for k in range(j))
            ell[i][j] = jnp.sqrt(jnp.maximum(s, 1e-300)) if i == j else s / ell[j][j]
    z = []
    for i in range(m):
        z.append((r[i] - sum(ell[i][k] * z[k] for k in range(i))) / ell[i][i])
    x = [None] * m
    for i in reversed(range(m)):
        x[i] = (z[i] - sum(ell[k][i] * x[k] for k in range(i + 1, m))) / ell[i][i]
    return jnp.stack(x)


def fit_recurrence(d: Array) -> Array:
    """Least-squares coefficients ``c`` of ``d[j + m] = sum_i c_i d[j + i]`` over the rows
    of ``d`` (differences, oldest first; ``m`` = :data:`ORDER`), columns scaled to unit
    norm and a 1e-12 relative ridge."""
    m = ORDER
    n_eq = d.shape[0] - m
    a = jnp.stack([d[i:i + n_eq].ravel() for i in range(m)], axis=1)  # (n_eq * n, m)
    b = d[m:].ravel()
    norm = jnp.maximum(jnp.sqrt(jnp.sum(a * a, axis=0)), 1e-300)
    a = a / norm
    g = a.T @ a + 1e-12 * jnp.eye(m)
    return _solve_spd(g, a.T @ b) / norm


#: Bits of the cycle count a jump may span (:func:`_power_and_sum`: each bit costs three
#: small matrix products per lane and round); a cell further than 1023 cycles from its
#: averaged ones integrates on until it is that close.
JUMP_BITS = 10


def _companion(c: Array) -> Array:
    """The matrix that moves a window of ``m`` consecutive differences one cycle on."""
    m = c.shape[0]
    return jnp.concatenate([jnp.eye(m, dtype=c.dtype)[1:], c[None]], axis=0)


def _power_and_sum(a: Array, n: Array) -> tuple[Array, Array]:
    """``(a^n, a + a^2 + ... + a^n)`` for an integer ``0 <= n < 2^JUMP_BITS`` by binary
    doubling: a fixed number of small matrix products, whatever ``n`` (no loop whose length
    differs between lanes)."""
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    power, total = eye, jnp.zeros_like(a)  # a^k and the sum up to k, k = bits taken so far
    p2, s2 = a, a  # a^(2^b) and its sum a + ... + a^(2^b)
    for b in range(JUMP_BITS):
        take = (n >> b) & 1
        total = jnp.where(take, total + power @ s2, total)
        power = jnp.where(take, power @ p2, power)
        s2, p2 = s2 + p2 @ s2, p2 @ p2
    return power, total


def predict(history: Array, cycle: Array, target: Array) -> tuple[Array, Array]:
    """The cycle-start state after ``target`` cycles, from the last :data:`HISTORY` ones.

    **Arguments:**

    - `history`: ``(HISTORY, n)`` ring of :func:`flatten`ed cycle-start states, the state
      after ``j`` cycles in row ``j % HISTORY``.
    - `cycle`: the completed cycles (the newest row); needs ``cycle >= HISTORY - 1`` (the
      engine starts at ``HISTORY``: it does not keep the start state).
    - `target`: the cycle to predict, ``>= cycle``.

    **Returns:**

    ``(x, error)``: the predicted flattened state, and the estimate of its error in the
    scaled units (``inf`` where the recurrence does not decay or the fit is not finite).
    """
    m = ORDER
    rows = (cycle - HISTORY + 1 + jnp.arange(HISTORY)) % HISTORY
    x = history[rows]  # oldest first
    d = jnp.diff(x, axis=0)  # (HISTORY - 1, n)
    newest_abs = jnp.max(jnp.abs(d[-1]))
    newest = jnp.maximum(newest_abs, 1e-300)
    # the check: fit without the newest difference, predict it
    c_old = fit_recurrence(d[:-1][-(3 * m):])
    guess = jnp.tensordot(c_old, d[-1 - m:-1], axes=1)
    eps = jnp.max(jnp.abs(guess - d[-1])) / newest
    c = fit_recurrence(d[-(3 * m):])

    powers, sums = _power_and_sum(_companion(c), target - cycle)
    total = jnp.tensordot(sums[-1], d[-m:], axes=1)  # the newest difference, summed forward
    last = jnp.tensordot(powers[-1], d[-m:], axes=1)
    size = jnp.max(jnp.abs(total))
    decays = jnp.max(jnp.abs(last)) <= newest_abs
    fits = decays & jnp.isfinite(size) & jnp.isfinite(eps) & (target - cycle < 2 ** JUMP_BITS)
    # a relative error eps in the modes' multipliers grows over the jump like the sum's
    # derivative: by ~1 / (1 - rate), which size / newest estimates
    error = jnp.where(fits, eps * size * (1.0 + size / newest), jnp.inf)
    return x[-1] + total, error


# --- the lane engine's use (jaxdea.engine.lanes.run_protocol, StepControl.extrapolate) ----

#: Lanes per pool that may try a jump in one round (:func:`jump`): the fit costs about a
#: step per lane, and at most this many per round keep it to ~4 % of a lane-step.
TRIES = 16


def record(lane, cycles, average):
    """Put each lane's newest cycle-start state (``lane.prev``) into its history, once per
    cycle.

    **Arguments:**

    - `lane`: the engine's pool of lanes (:class:`jaxdea.engine.lanes._Lane`, leading axis
      = lanes) at the end of a round.
    - `cycles`, `average`: the protocol's cycle budget and averaged cycles.

    **Returns:**

    ``(lane, want)``: the lanes with their history updated, and which of them may try a
    jump now (a new cycle recorded, :data:`HISTORY` consecutive ones in the history, at
    least two cycles before the averaged ones). A lane that completed two cycles within
    one round misses a state: its streak starts again.
    """
    new = lane.cycle > lane.recorded
    slot = lane.cycle % HISTORY
    rows = jax.vmap(flatten)(lane.prev).astype(lane.history.dtype)
    lanes = jnp.arange(slot.shape[0])
    history = lane.history.at[lanes, slot].set(
        jnp.where(new[:, None], rows, lane.history[lanes, slot]))
    streak = jnp.where(new, jnp.where(lane.cycle == lane.recorded + 1, lane.streak + 1, 1),
                       lane.streak)
    lane = eqx.tree_at(lambda s: (s.history, s.recorded, s.streak), lane,
                       (history, jnp.where(new, lane.cycle, lane.recorded), streak))
    want = new & ~lane.done & (streak >= HISTORY) & (lane.cycle <= cycles - average - 2)
    return lane, want


def jump(lane, want, cycles, average, tol):
    """The lanes ``want`` whose transient extrapolates to within ``tol`` (:func:`predict`),
    and where they jump: the start of the averaged cycles.

    **Arguments:**

    - `lane`, `want`: from :func:`record`.
    - `cycles`, `average`: the protocol's cycle budget and averaged cycles.
    - `tol`: the largest accepted error estimate (scaled units).

    **Returns:**

    ``(go, moved)``: which lanes jump, and every lane as it would be after a jump (the
    caller selects ``moved`` where ``go``): cycle ``cycles - average`` from the predicted
    state with a fresh window (and the step size it had proposed), never to jump again. At
    most :data:`TRIES` lanes try per call; the others try again after their next cycle.
    """
    n = want.shape[0]
    idx = jnp.nonzero(want, size=min(TRIES, n), fill_value=n)[0]
    safe = jnp.minimum(idx, n - 1)
    target = (cycles - average) + jnp.zeros(n, lane.cycle.dtype)
    x, error = jax.vmap(predict)(lane.history[safe], lane.cycle[safe], target[safe])
    go = jnp.zeros(n, bool).at[idx].set(error < tol, mode="drop")
    x = jnp.zeros((n, x.shape[1]), x.dtype).at[idx].set(x, mode="drop")
    y = jax.vmap(unflatten)(x, lane.y)
    # h stays the step the lane proposed mid-cycle: restarting at a fresh cell's first step
    # (T/200) put P_out 4e-5 and the amplitude 1e-3 off the full run (64 cells at 60-200 Hz;
    # 8e-6 and 8e-5 this way): the step control then under-resolves the first step after
    # the edge
    moved = eqx.tree_at(
        lambda s: (s.y, s.cycle, s.u, s.window, s.wcycle, s.prev, s.res, s.ratio, s.rate,
                   s.back, s.xmin, s.xmax, s.streak),
        lane, (y, target, jnp.zeros(n), y, target, y, jnp.full(n, jnp.inf), jnp.ones(n),
               jnp.ones(n), jnp.zeros_like(lane.back), jnp.full(n, jnp.inf),
               jnp.full(n, -jnp.inf), jnp.full(n, -(2 ** 30), jnp.int32)))
    return go, moved
