"""What the lane engine reports per cell: status codes, cycle metrics, and their pieces.

The window averages are differences of the energy accumulators at the window ends
(:func:`window_metrics`); the payload amplitude is the extremum of the cubic Hermite
interpolant of every accepted step (:func:`hermite_extrema`); the periodicity residual
(:func:`periodicity_residual`) and its contraction rate decide when a cell has settled
(:func:`settled`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..models.cone import ConeState, hermite_coefficients
from ..models.cone import returned_charge as returned_charge  # re-export: the step's math
from .step_control import SCALES

#: Meaning of the ``status`` values a cell can get (0 = ok).
STATUS = {
    0: "ok",
    1: "Gent lock-up: a stretch reached the limiting-chain limit",
    2: "non-finite state (pull-in / electromechanical instability or overflow)",
    3: "step budget exhausted before the last cycle",
    4: "not converged: no stable periodic steady state reached (residual above tolerance, "
       "or the periodic orbit found is unstable)",
}

#: Periodicity residual (:func:`periodicity_residual`) above which a cell's last cycles are
#: not periodic: its averages are not a steady-state power (:func:`steady_cells`; the
#: evidence for the value is in docs/models.md, section 4, *Steady cells*).
STEADY_RESIDUAL = 1e-3


def steady_cells(status, residual, threshold: float = STEADY_RESIDUAL):
    """Which cells ran their last cycle to the end and repeated it: status 0 or 4 (not
    stopped by lock-up, a non-finite state or the step budget) and a finite periodicity
    residual at most ``threshold``.

    **Arguments:**

    - `status`: the cells' status codes (:data:`STATUS`).
    - `residual`: their periodicity residuals.
    - `threshold`: the largest residual of a steady cell (:data:`STEADY_RESIDUAL`).

    **Returns:**

    A boolean numpy array of the same shape.
    """
    status, residual = np.asarray(status), np.asarray(residual, dtype=float)
    finished = (status == 0) | (status == 4)
    with np.errstate(invalid="ignore"):
        return finished & np.isfinite(residual) & (residual <= threshold)


class CycleMetrics(eqx.Module):
    """Per-cell results of the protocol (SI units), each with the batch's shape."""

    P_out: Array  #: mean payload power over the window, W (eq 19)
    P_in: Array  #: mean electrical input power, no energy recovery, W (eq 20)
    P_in_signed: Array  #: mean of Phi_in i (charge returned to the source counts), W
    efficiency: Array  #: P_out / P_in (eq 21)
    amplitude: Array  #: half peak-to-peak payload displacement over the window, m
    v_rms: Array  #: RMS payload velocity over the window, m/s
    status: Array  #: 0 = ok, see STATUS
    steps: Array  #: solver steps taken (accepted + rejected)
    residual: Array  #: periodicity residual over the last cycle (:func:`periodicity_residual`)
    cycles_run: Array  #: drive cycles integrated for the cell
    final_state: ConeState  #: state at the end of the last cycle


def _hermite(x0, v0, x1, v1, h):
    """Hermite coefficients ``(a, b)`` and the (clipped, sorted) roots in [0, h] of the cubic's
    derivative."""
    a, b = hermite_coefficients(x0, v0, x1, v1, h)
    qa, qb, qc = 3.0 * b, 2.0 * a, v0  # x'(s) = qc + qb s + qa s^2
    sq = jnp.sqrt(jnp.maximum(qb * qb - 4.0 * qa * qc, 0.0))
    quad = jnp.abs(qa) * h > 1e-12 * (jnp.abs(qb) + jnp.abs(qc) / h + 1e-300)
    safe_qa = jnp.where(quad, qa, 1.0)
    lin_ok = jnp.abs(qb) > 0
    lin_root = jnp.where(lin_ok, -qc / jnp.where(lin_ok, qb, 1.0), 0.0)
    r1 = jnp.where(quad, (-qb - sq) / (2.0 * safe_qa), lin_root)
    r2 = jnp.where(quad, (-qb + sq) / (2.0 * safe_qa), lin_root)
    r1, r2 = jnp.clip(r1, 0.0, h), jnp.clip(r2, 0.0, h)
    return a, b, jnp.stack([jnp.minimum(r1, r2), jnp.maximum(r1, r2)])


def _cubic(x0, v0, a, b, s):
    return x0 + s * (v0 + s * (a + s * b))


def hermite_extrema(x0, v0, x1, v1, h):
    """Extrema of the cubic Hermite interpolant over one step.

    **Arguments:**

    - `x0`, `v0`: position and velocity at the start of the step.
    - `x1`, `v1`: position and velocity at its end.
    - `h`: the step length.

    **Returns:**

    ``(min, max)`` over [0, h] of the cubic matching (x, x') at both ends.
    """
    a, b, roots = _hermite(x0, v0, x1, v1, h)
    cand = jnp.concatenate([_cubic(x0, v0, a, b, roots), jnp.stack([x0, x1])])
    return jnp.min(cand, axis=0), jnp.max(cand, axis=0)


class Dynamics(NamedTuple):
    """The dynamical states of a :class:`~jaxdea.models.cone.ConeState` (:data:`DYNAMICAL`):
    what the lane engine keeps of a cycle's start state, for the periodicity residual.
    Carrying these five leaves instead of all eight is three selects fewer per lane-step."""

    q: Array
    v: Array
    charge: Array
    xi_m: Array
    xi_el: Array


#: The states that define the dynamics (the rest are energy accumulators).
DYNAMICAL = Dynamics._fields


class Energies(NamedTuple):
    """The energy accumulators of a :class:`~jaxdea.models.cone.ConeState`: what the lane
    engine keeps of the state at its averaging window's start (the window's averages are
    their differences, :func:`window_metrics`; five selects fewer per lane-step than the
    whole state)."""

    payload_work: Array
    v2: Array
    energy_in: Array


def dynamics(y: ConeState) -> Dynamics:
    """``y``'s dynamical states (:class:`Dynamics`)."""
    return Dynamics(*(getattr(y, k) for k in DYNAMICAL))


def energies(y: ConeState) -> Energies:
    """``y``'s energy accumulators (:class:`Energies`)."""
    return Energies(y.payload_work, y.v2, y.energy_in)


def periodicity_residual(y1: ConeState | Dynamics, y0: ConeState | Dynamics) -> Array:
    """How far a cycle is from periodic.

    **Arguments:**

    - `y1`, `y0`: the states at the end and at the start of the cycle (or their
      :class:`Dynamics`).

    **Returns:**

    The scaled max-norm of ``y1 - y0`` over the dynamical states (:data:`DYNAMICAL`):
    ``|dy| / (s + |y|)`` with the absolute scales ``s`` of the step-error norm (1 mm,
    0.1 m/s, 1 uC, 1; :data:`~jaxdea.engine.step_control.SCALES`).
    """
    worst = jnp.zeros(())
    for name in DYNAMICAL:
        a, b = getattr(y1, name), getattr(y0, name)
        scale = SCALES[name][0]
        r = jnp.abs(a - b) / (scale + jnp.maximum(jnp.abs(a), jnp.abs(b)))
        worst = jnp.maximum(worst, jnp.max(r))
    return worst


def settled(res, rate, tol):
    """Whether a cell's one-period map has converged.

    **Arguments:**

    - `res`: periodicity residual of the last cycle.
    - `rate`: observed contraction of the residual per cycle.
    - `tol`: tolerance.

    **Returns:**

    True when the residual, scaled up by the distance still to go at the observed geometric
    rate (``res * rate / (1 - rate)``), is below ``tol``.
    """
    rate = jnp.clip(rate, 0.0, 0.999)
    return res * jnp.maximum(1.0, rate / (1.0 - rate)) < tol


def all_finite(y: ConeState) -> Array:
    """Finite check on the dynamical states (a NaN anywhere reaches these within a step)."""
    return jnp.isfinite(jnp.sum(y.q) + jnp.sum(y.v) + jnp.sum(y.charge) + jnp.sum(y.xi_m)
                        + jnp.sum(y.xi_el))


def window_metrics(lane, cycles, settle, require_settled: bool) -> dict[str, Array]:
    """One lane's metrics over its averaging window (the fields of :class:`CycleMetrics`
    but the final state).

    **Arguments:**

    - `lane`: one lane of the engine (:func:`jaxdea.engine.lanes.run_protocol`'s record:
      the current state and the window-start :class:`Energies`, cycle counts, residual,
      contraction rate, returned energy, payload extrema, lock-up flag and step count).
    - `cycles`: the cycle budget.
    - `settle`: the settling tolerance, or None.
    - `require_settled`: whether a cell that never settles fails (status 4).

    **Returns:**

    ``{name: value}`` for P_out, P_in, P_in_signed, efficiency, amplitude, v_rms, status,
    steps, residual and cycles_run.
    """
    w, y = lane.window, lane.y
    span = (lane.cycle - lane.wcycle) / lane.loading.drive.frequency
    p_out = (y.payload_work - w.payload_work) / span
    e_in = y.energy_in - w.energy_in
    p_in_signed = jnp.sum(e_in) / span
    p_in = (jnp.sum(e_in) - jnp.sum(lane.back)) / span  # back: the driven membranes only
    eff = jnp.where(p_in > 0, p_out / jnp.where(p_in > 0, p_in, 1.0), 0.0)
    finite = all_finite(y)
    done = False if settle is None else settled(lane.res, lane.rate, settle)
    unfinished = (lane.cycle < cycles) & ~done  # stopping early once settled is no failure
    ok = jnp.where(done, 0, 4) if settle is not None and require_settled else 0
    status = jnp.where(
        ~finite, 2, jnp.where(lane.lockup, 1, jnp.where(unfinished, 3, ok))
    ).astype(jnp.int32)
    return dict(
        P_out=p_out,
        P_in=p_in,
        P_in_signed=p_in_signed,
        efficiency=eff,
        amplitude=0.5 * (lane.xmax - lane.xmin),
        v_rms=jnp.sqrt(jnp.maximum(y.v2 - w.v2, 0.0) / span),
        status=status,
        steps=lane.steps,
        residual=lane.res,
        cycles_run=lane.cycle,
    )
