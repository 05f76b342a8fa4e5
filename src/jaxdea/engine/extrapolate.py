"""Extrapolation of a cell's slow transient: the state after many more cycles, from the last few.

Why: in the papers' protocol (N cycles from rest, the last k averaged) a lightly damped cell
at a high frequency decays by only a few per cent per cycle, so it runs 60-100 of its cycles
before its early exit fires or its budget ends, although after ~20 cycles its transient is
already a sum of a few geometric modes. Then the cycle-start states ``x_j`` (the one-period
map's iterates) obey a linear recurrence of low order ``m`` in their differences
``d_j = x_{j+1} - x_j``::

    d_{j+m} = c_0 d_j + c_1 d_{j+1} + ... + c_{m-1} d_{j+m-1}

(the minimal polynomial of the period map's slowest Floquet multipliers, complex pairs
included), and the state after a later cycle ``L`` is ``x_n`` plus the recurrence's
differences summed forward. The lane engine (:func:`jaxdea.engine.lanes.run_protocol`,
``StepControl(extrapolate=...)``, runs with an early exit only) jumps to
``L = N - k -`` :data:`LOOKAHEAD` with the step size of its last cycle end, and integrates on
from there as any cell does: its early exit finds it periodic a few cycles later (one cycle
is then averaged), or it runs its last cycles and averages ``k``. So a jump changes where
the transient is cut short, not the criterion: the answers are the early exit's, to ~1e-6
(``bench/NOTES.md``).

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
from .lane_state import scatter_each
from .metrics import DYNAMICAL, Dynamics, dynamics, energies
from .step_control import SCALES

#: Order of the fitted recurrence (modes of the transient); measured on 64 DCDEA-LS cells at
#: 60-200 Hz (``bench/NOTES.md``): order 2 and 3 left 1e-2 errors where 4 reached the
#: integration's own noise.
ORDER = 4
#: Cycle-start states kept per lane: the ``3 m + 1`` of the fit and one more for the check.
HISTORY = 3 * ORDER + 2


def flatten(y: ConeState | Dynamics) -> Array:
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


def predict(history: Array, cycle: Array, target: Array) -> tuple[Array, Array, Array]:
    """The cycle-start state after ``target`` cycles, from the last :data:`HISTORY` ones.

    **Arguments:**

    - `history`: ``(HISTORY, n)`` ring of :func:`flatten`ed cycle-start states, the state
      after ``j`` cycles in row ``j % HISTORY``.
    - `cycle`: the completed cycles (the newest row); needs ``cycle >= HISTORY - 1`` (the
      engine starts at ``HISTORY``: it does not keep the start state).
    - `target`: the cycle to predict, ``>= cycle``.

    **Returns:**

    ``(x, error, step)``: the predicted flattened state, the estimate of its error in the
    scaled units (``inf`` where the recurrence does not decay or the fit is not finite), and
    the predicted size (largest component) of the difference there, which the first cycle
    after a jump checks (:func:`verify`).
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
    return x[-1] + total, error, jnp.max(jnp.abs(last))


# --- the lane engine's use (jaxdea.engine.lanes.run_protocol, StepControl.extrapolate) ----

#: Cycles a jump lands before the averaged ones (:func:`landing_cycle`): the cell then runs
#: them as any cell of the protocol does, so its early exit can find it periodic (it needs
#: three cycle ends after a landing to measure the contraction) and stop it with its usual
#: one-cycle window; a cell whose landing is not periodic by then averages its last cycles
#: as usual. Measured on 128 DCDEA-LS cells at 60-200 Hz, jumped at cycle 30 with the
#: step of the cycle's end carried: median 3 cycles after the landing to the early exit.
LOOKAHEAD = 5


def landing_cycle(cycles, average):
    """The cycle a jump lands at: :data:`LOOKAHEAD` cycles before the ``average`` averaged
    cycles of a ``cycles`` budget."""
    return cycles - average - LOOKAHEAD


#: A jump needs two consecutive cycles' predictions of its landing to agree within this many
#: times the tolerance (:func:`jump`). Why: the fit's own check (predict the newest
#: difference) can pass on a recurrence with a spurious mode that the long sum amplifies. At
#: a DCDEA-LS cell (M 10 g, c 2.9 N s/m, 185 Hz) the estimate at cycle 41 was 7e-8 and the
#: landing 4.9e-3 off (P_out 7e-4, amplitude 1.6e-2 off the full run), where the
#: predictions of cycles 40 and 42 were 1.7e-4 and 2e-8 off.
AGREE = 10.0

#: Lanes whose jumps are fitted together (:func:`jump`): every lane that recorded a new cycle
#: tries in the same round, in batches of this many, or more in a wide pool
#: (:func:`try_width`). A vmap over the whole pool every round cost +27 % per lane-step,
#: batches of 16 +4 %.
TRIES = 16
#: A pool wider than ``TRIES x TRY_BATCHES`` lanes (an accelerator's, as wide as a chunk)
#: fits its lanes in batches of ``1/TRY_BATCHES`` of its width instead (:func:`jump`): each
#: batch launches the fit's 77-94 kernels (125-180 us for 16 lanes on this project's CPUs),
#: and in batches of 16 a pool of 10^5 lanes with a quarter of them at a cycle end would
#: launch them thousands of times a round.
TRY_BATCHES = 8


def try_width(n_lanes: int) -> int:
    """Lanes fitted together in a pool of ``n_lanes`` (:func:`jump`): :data:`TRIES`, or
    ``1/``:data:`TRY_BATCHES` of a wider pool, so that a round fits its lanes in at most
    :data:`TRY_BATCHES` batches."""
    return min(n_lanes, max(TRIES, -(-n_lanes // TRY_BATCHES)))


def record(lane, cycles, average):
    """Put each lane's newest cycle-start state (``lane.prev``) into its history, once per
    cycle.

    **Arguments:**

    - `lane`: the engine's pool of lanes (:class:`jaxdea.engine.lane_state.Lane`, leading axis
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
    want = new & ~lane.done & (streak >= HISTORY) & (
        lane.cycle <= landing_cycle(cycles, average) - 2)
    return lane, want


def jump(lane, want, cycles, average, tol):
    """The lanes ``want`` whose transient extrapolates to within ``tol`` (:func:`predict`),
    and where they jump: :data:`LOOKAHEAD` cycles before the averaged ones.

    **Arguments:**

    - `lane`, `want`: from :func:`record`.
    - `cycles`, `average`: the protocol's cycle budget and averaged cycles.
    - `tol`: the largest accepted error estimate (scaled units).

    **Returns:**

    ``(go, moved, tried)``: which lanes jump, every lane as it would be after a jump, and
    every lane as it would be without one (the caller selects ``moved`` where ``go``, else
    ``tried``). A jump lands at cycle :func:`landing_cycle` on the predicted state with a
    fresh window and periodicity record and the step size the lane proposed at its last
    cycle end, never to jump again, keeping where it jumped from for :func:`verify`. A lane
    jumps only when its error estimate is below ``tol`` and its prediction agrees within
    :data:`AGREE` ``tol`` with the one it made a cycle before (both lanes keep the
    prediction for the next cycle).
    Every lane in ``want`` tries now, :data:`TRIES` at a time, so a cell's jump depends on
    its own history only, not on how many other lanes of its pool completed a cycle in the
    same round (the pool's width and its tail pools do not change a cell's result).
    """
    n = want.shape[0]
    k = try_width(n)
    target = jnp.full(k, landing_cycle(cycles, average), lane.cycle.dtype)

    def batch(carry):
        go, x_all, step_all, left = carry
        idx = jnp.nonzero(left, size=k, fill_value=n)[0]
        safe = jnp.minimum(idx, n - 1)
        x, error, step = jax.vmap(predict)(lane.history[safe], lane.cycle[safe], target)
        agree = (lane.guessed[safe] == lane.cycle[safe] - 1) & (
            jnp.max(jnp.abs(x - lane.guess[safe]), axis=1) <= AGREE * tol)
        return scatter_each((go, x_all, step_all, left), idx,
                            ((error < tol) & agree, x, step, jnp.zeros(k, bool)))

    x0 = jnp.zeros((n, lane.history.shape[-1]), lane.history.dtype)
    go, x, step, _ = jax.lax.while_loop(lambda c: jnp.any(c[-1]), batch,
                                        (jnp.zeros(n, bool), x0, jnp.zeros(n, x0.dtype), want))
    tried = eqx.tree_at(lambda s: (s.guess, s.guessed), lane,
                        (jnp.where(want[:, None], x, lane.guess),
                         jnp.where(want, lane.cycle, lane.guessed)))
    y = jax.vmap(unflatten)(x, lane.y)
    target = jnp.full(n, landing_cycle(cycles, average), lane.cycle.dtype)
    # the landing goes on with the step the lane proposed at its last cycle end: the step
    # sequence is part of the discrete orbit. Restarted at a fresh cell's first step (T/200)
    # the landing's cycles are another discretisation, ~4e-5 (scaled) off, whose transient
    # must decay again (P_out 4e-5 and the amplitude 1e-3 off the full run, 64 cells at
    # 60-200 Hz); with the step proposed mid-cycle, 8e-6 and 8e-5; with the cycle end's,
    # the landed cells meet the early exit a median 3 cycles on, within 4e-8 (P_out) and
    # 6e-7 (amplitude) of the run without a jump (128 cells at 60-200 Hz)
    newest = lane.history[jnp.arange(n), lane.cycle % HISTORY]
    moved = eqx.tree_at(
        lambda s: (s.streak, s.origin, s.landing, s.jumped_from, s.expect, s.h),
        _restart(tried, y, target),
        (jnp.full(n, -(2 ** 30), jnp.int32), newest, x, lane.cycle, step, lane.hwrap))
    return go, moved, tried


def _restart(lane, y, cycle):
    """``lane`` at the start of cycle ``cycle`` from state ``y``, with a fresh window and
    periodicity record (a jump's landing, or a taken-back jump's origin)."""
    n = cycle.shape[0]
    return eqx.tree_at(
        lambda s: (s.y, s.cycle, s.u, s.window, s.wcycle, s.prev, s.res, s.ratio, s.rate,
                   s.back, s.xmin, s.xmax),
        lane, (y, cycle, jnp.zeros(n), energies(y), cycle, dynamics(y), jnp.full(n, jnp.inf),
               jnp.ones(n), jnp.ones(n), jnp.zeros_like(lane.back), jnp.full(n, jnp.inf),
               jnp.full(n, -jnp.inf)))


#: A jump is taken back when the first cycle after it moves the state by more than the
#: predicted difference plus this many times the tolerance (:func:`verify`). At tol 1e-7, on
#: 64 DCDEA-LS cells at 60-200 Hz and 5 SCDEA-LS cells under a Coulomb drag (60-200 Hz):
#: 100 took back many good jumps (2.20x -> 1.63x fewer steps than the early exit alone),
#: 1000 few (2.01x) and caught the drag's bad one (P_out 4.1e-4 -> 4.9e-5, amplitude
#: 3.7e-3 -> 1.6e-4 off the full run); 10 000 missed it. The integration's own cycle-to-
#: cycle noise after a restart is ~1e-5-1e-4 in these units, so a tighter check cannot
#: tell a good landing from a bad one.
VERIFY = 1000.0


def verify(lane, cycles, average, tol):
    """The first cycle after a jump, checked: its difference ``x_{k+1} - x_k`` (``k`` the
    cycle jumped to) against the one the fit predicted there.

    A transient the recurrence does not describe (a stick-slip payload's, say) can pass the
    fit's own check and still land off the trajectory; the cycle after the landing then
    moves the state by about the landing's error. Such a lane goes back to the cycle-start
    state it jumped from and integrates on from there, never to jump again; the others keep
    their jump.

    **Arguments:**

    - `lane`: the engine's pool of lanes at the end of a round.
    - `cycles`, `average`: the protocol's cycle budget and averaged cycles.
    - `tol`: the extrapolation's tolerance (scaled units).

    **Returns:**

    ``(back, undone, kept)``: which lanes go back, every lane as it would be after going
    back, and every lane as it is (the caller selects ``undone`` where ``back``, else
    ``kept``); in both, a checked lane's record of its jump is cleared.
    """
    n = lane.cycle.shape[0]
    landed = landing_cycle(cycles, average)
    checked = (lane.jumped_from >= 0) & (lane.cycle > landed)
    moved = jnp.max(jnp.abs(jax.vmap(flatten)(lane.prev).astype(lane.landing.dtype)
                            - lane.landing), axis=1)
    back = checked & (lane.cycle == landed + 1) & ~lane.lockup \
        & ~(moved <= lane.expect + VERIFY * tol)
    kept = eqx.tree_at(lambda s: s.jumped_from, lane, jnp.where(checked, -1, lane.jumped_from))
    y = jax.vmap(unflatten)(lane.origin, lane.y)
    # back at a cycle start, with a cycle end's step (as a landing: see jump)
    undone = eqx.tree_at(lambda s: (s.done, s.h),
                         _restart(kept, y, jnp.maximum(lane.jumped_from, 0)),
                         (jnp.zeros(n, bool), lane.hwrap))
    return back, undone, kept
