"""Adaptive step-size control of the lane engine: the policy, the error norm, the controller.

:class:`StepControl` is the user-facing policy (tolerance, largest step, step budget).
:class:`IController` turns one attempted step's error estimate into accept/reject and the
next step size, in the shape of diffrax's ``AbstractStepSizeController.adapt_step_size``:
a standard integral controller on the scaled RMS error (:func:`error_norm`, weights
:data:`SCALES`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import SweepError, check_choice, check_int, check_unit_interval
from ..models.cone import ConeState


class StepControl(NamedTuple):
    """Adaptive-step policy.

    ``rtol``: relative tolerance on the mechanical, dashpot and charge states (scaled RMS
    norm); ``dt_max``: largest step, s (explicit-RK4 stability of the mechanics needs < ~3 ms);
    ``max_steps``: per-cell step budget (status 3 when exhausted); ``precision``: ``"double"``
    (the default) or ``"single"``: the lanes' dynamical states (positions, velocities,
    charges, dashpot stretches) and the model's parameters in float32, time, step sizes and
    the energy integrals in float64 (:mod:`jaxdea.engine.precision`, which also says what
    single precision refuses); ``solver``: ``"lawson"`` (the default,
    :class:`~jaxdea.solver.LawsonRK4`) or ``"exponential"``
    (:class:`~jaxdea.solver.ExponentialRK4`: ~2x more accurate against LSODA at the same
    ``rtol``, 5-15 % slower on the power-map bench; ``rtol=2e-6`` with it is as accurate as
    Lawson at 1e-6 on viscous payloads in 1.4x fewer steps, not on a Coulomb drag:
    ``bench/NOTES.md``); ``extrapolate``: a tolerance in (0, 1), ``None`` (off) or
    ``"auto"`` (the default: :data:`EXTRAPOLATE` for a map or sweep of at least
    :data:`EXTRAPOLATE_FROM` cells with an early exit, else off;
    :func:`resolve_extrapolate`): in the papers'
    and the continuation protocol with an early exit, a cell whose slow transient fits a
    low-order linear recurrence of its cycle-start states to this estimated error (scaled
    units) jumps a few cycles short of its averaged ones and integrates on from there, so
    that the early exit finds it periodic there instead of after the cycles in between
    (:mod:`jaxdea.engine.extrapolate`; the same answer to ~1e-6 in fewer steps,
    ``bench/NOTES.md``). Runs without an early exit never jump.
    """

    rtol: float = 1e-6
    dt_max: float = 1e-3
    max_steps: int = 5_000_000
    precision: str = "double"
    solver: str = "lawson"
    extrapolate: float | str | None = "auto"


#: ``StepControl(extrapolate="auto")``: the tolerance of a job of at least
#: :data:`EXTRAPOLATE_FROM` cells. Measured on 1024 DCDEA-LS cells at 1-200 Hz (papers'
#: protocol, early exit): 1e-8 0.69x the steps, 0.78x the time, P_out within 1.4e-6 of the
#: run without jumps (amplitude 7.2e-6); 1e-7 0.63x, 0.74x, 1.2e-5 (1.8e-5).
EXTRAPOLATE = 1e-8
#: ``"auto"`` extrapolates from this many cells on: its compiled code costs ~1.6 s per lane
#: pool (3.3 s for a batch's two), which the jumps repay (~0.2 ms per cell of the papers'
#: protocol on two CPU devices) from ~18 000 cells; smaller jobs (the tests, the README's
#: main job) compile without it.
EXTRAPOLATE_FROM = 20_000
#: The default of :attr:`StepControl.extrapolate`.
AUTO = "auto"


def resolve_extrapolate(control: StepControl, n_cells: int,
                        early_exit: float | None) -> StepControl:
    """``control`` with ``extrapolate="auto"`` replaced by its value for a job of
    ``n_cells`` cells: :data:`EXTRAPOLATE` from :data:`EXTRAPOLATE_FROM` cells on, else
    ``None``; ``None`` too without an early exit (nothing jumps there) and in single
    precision (whose cycle-to-cycle noise, ~1e-5, no fit gets under). A tolerance or
    ``None`` stays as it is.

    **Arguments:**

    - `control`: the step policy.
    - `n_cells`: the job's cells (a whole map's or sweep's, not a chunk's: every chunk of a
      job runs the same way).
    - `early_exit`: the job's early exit (``None``: every cell runs all its cycles).

    **Returns:**

    The step policy with ``extrapolate`` a tolerance or ``None``.
    """
    if isinstance(control.extrapolate, str) and control.extrapolate == AUTO:
        on = (n_cells >= EXTRAPOLATE_FROM and control.precision == "double"
              and early_exit is not None)
        return control._replace(extrapolate=EXTRAPOLATE if on else None)
    return control


#: The lanes' precisions (:class:`StepControl`; what single precision may be combined with:
#: :func:`jaxdea.engine.precision.check_precision`).
PRECISIONS = ("double", "single")
#: The lanes' solvers (:class:`StepControl`).
SOLVERS = ("lawson", "exponential")


def check_control(control) -> None:
    """Check a step policy.

    **Arguments:**

    - `control`: should be a :class:`StepControl` with ``0 < rtol < 1``, ``dt_max > 0`` and
      an integer ``max_steps >= 1``, a known ``precision`` and ``solver``.

    **Returns:**

    Nothing; raises :class:`~jaxdea.SweepError` naming the offending field otherwise.
    """
    if not isinstance(control, StepControl):
        raise SweepError("control must be a jaxdea.StepControl")
    check_unit_interval("rtol", control.rtol)
    dt_max = control.dt_max
    if isinstance(dt_max, bool) or not isinstance(dt_max, (int, float, np.floating)) \
            or not (math.isfinite(dt_max) and dt_max > 0):
        raise SweepError(f"dt_max = {dt_max!r} must be > 0 (allowed range (0, inf))")
    check_int("max_steps", control.max_steps, 1)
    if control.precision not in PRECISIONS:
        raise SweepError(f"precision = {control.precision!r} must be one of "
                         f"{', '.join(map(repr, PRECISIONS))}")
    check_choice("solver", control.solver, SOLVERS)
    if isinstance(control.extrapolate, str):
        if control.extrapolate != AUTO:
            raise SweepError(f"extrapolate = {control.extrapolate!r} must be a tolerance in "
                             f"(0, 1), None (off) or {AUTO!r}")
    elif control.extrapolate is not None:
        check_unit_interval("extrapolate", control.extrapolate)


def control_attrs(control: StepControl, protocol: str) -> dict:
    """The step policy as a map's or sweep's metadata: ``rtol``, ``precision``, ``solver``
    and ``extrapolate`` (``None`` where ``protocol`` is ``"periodic"``, which ignores it)."""
    extrapolate = control.extrapolate if protocol != "periodic" else None
    if isinstance(extrapolate, str):  # "auto" not resolved: the engine runs it as off
        extrapolate = None
    return dict(rtol=float(control.rtol), precision=control.precision, solver=control.solver,
                extrapolate=None if extrapolate is None else float(extrapolate))


#: Error weights of the states: the tolerance on a state is ``rtol * w * (s + |y|)`` with
#: ``(s, w)`` below (SI). Charge gets a 10x tighter weight because P_in needs the current
#: ``i = (Phi - Q/C) / 2R_s``, which amplifies charge errors by ``1/(2 R_s C)`` ~ 2e4 /s.
#: (Measured on the 996-f DCDEA-LS sweep against LSODA rtol 1e-9 at 7 frequencies: weight
#: 1e-2 -> max error 5e-5 with 1.26x the steps of 1e-1 -> 4e-5; weight 1 -> 2e-4 on P_in.)
SCALES = dict(q=(1e-3, 1.0), v=(0.1, 1.0), charge=(1e-6, 1e-1), xi_m=(1.0, 1.0),
              xi_el=(1.0, 1.0))
#: Below this drive frequency the charge's error weight shrinks in proportion to the frequency
#: (:func:`charge_weight`), Hz. Why: P_in without recovery integrates the current's negative
#: part, and in the slow phases of a low-frequency cycle (the membrane creeps after its
#: ringing has died out) that current is ``kappa`` times the charge's tiny lag behind
#: ``C Phi``; the step's charge error is of the same size, and it accumulates over the cycle's
#: duration, ``1/f``, against one charge per cycle of input. Measured against LSODA (rtol
#: 1e-8, DCDEA-LS, M 0.26 g, c 0.26 N s/m): P_in off by 3.8e-3 / 1.2e-3 / 1.1e-3 at 1 / 2 /
#: 3 Hz with the fixed weight 1e-1 (P_in_signed and P_out right to 2e-6 and 2e-4); a
#: per-cycle budget, weight 1e-1 x f / 30 Hz below 30 Hz, brings P_in within 2e-4 for 11-35 %
#: more steps at 1-5 Hz and none above 30 Hz (docs/models.md, section 4).
CHARGE_WEIGHT_FREQUENCY = 30.0


def charge_weight(frequency: Array) -> Array:
    """The charge's error weight for a cell driven at ``frequency`` (Hz): :data:`SCALES`'
    weight, times ``f / CHARGE_WEIGHT_FREQUENCY`` below :data:`CHARGE_WEIGHT_FREQUENCY`."""
    return SCALES["charge"][1] * jnp.minimum(1.0, frequency / CHARGE_WEIGHT_FREQUENCY)


def error_norm(err: ConeState, y0: ConeState, y1: ConeState, rtol,
               charge: Array | None = None) -> Array:
    """Scaled RMS norm of the local error over the dynamical states (not the accumulators).

    **Arguments:**

    - `err`: the solver's local error estimate of the step.
    - `y0`, `y1`: the states at the start and end of the step.
    - `rtol`: relative tolerance.
    - `charge`: the charge's error weight (e.g. :func:`charge_weight` of the cell's
      frequency; ``None``: :data:`SCALES`' weight).

    **Returns:**

    ``sqrt(mean(r^2))`` over every component of :data:`SCALES`' states, with
    ``r = err / (rtol * w * (s + max(|y0|, |y1|)))``; a step is acceptable when this is <= 1.
    """
    total, count = 0.0, 0
    for name, (scale, weight) in SCALES.items():
        if name == "charge" and charge is not None:
            weight = charge
        e = getattr(err, name)
        ref = jnp.maximum(jnp.abs(getattr(y0, name)), jnp.abs(getattr(y1, name)))
        r = e / (rtol * weight * (scale + ref))
        total = total + jnp.sum(r * r)
        count += r.size
    return jnp.sqrt(total / count)


class IController(eqx.Module):
    """Integral step-size controller: ``h_next = h * clip(safety * norm**exponent, ...)``.

    **Arguments:**

    - `rtol`: relative tolerance of :func:`error_norm`.
    - `dt_max`: largest step, s.
    - `safety`, `exponent`: ``0.9`` and ``-1/4`` (the error estimate is of order 3).
    - `factormin`, `factormax`: clip of the step-size factor (``0.2 .. 4``); a non-finite
      error norm takes ``factormin``.
    """

    rtol: float
    dt_max: float
    safety: float = eqx.field(static=True, default=0.9)
    exponent: float = eqx.field(static=True, default=-0.25)
    factormin: float = eqx.field(static=True, default=0.2)
    factormax: float = eqx.field(static=True, default=4.0)

    def adapt_step_size(self, y0: ConeState, y1_candidate: ConeState, y_error: ConeState,
                        h: Array, h_prev: Array, clipped: Array,
                        active: Array, charge: Array | None = None
                        ) -> tuple[Array, Array, Array]:
        """Accept or reject one attempted step and propose the next step size.

        **Arguments:**

        - `y0`: the state at the start of the step.
        - `y1_candidate`: the state at its end (not yet accepted).
        - `y_error`: the solver's local error estimate.
        - `h`: the step just attempted, s.
        - `h_prev`: the step size proposed before (``h`` is it, or less when the step was
          clipped to a node of the cycle).
        - `clipped`: whether ``h`` was clipped to a node: an accepted clipped step does not
          shrink the next proposal below ``h_prev``.
        - `active`: whether the lane is running; an idle lane keeps ``h_prev``.
        - `charge`: the charge's error weight (:func:`error_norm`; default :data:`SCALES`').

        **Returns:**

        ``(accept, ok, h_next)``: ``accept = active & ok``; ``ok``: the error norm is <= 1 (a
        non-finite candidate fails this: its states enter the norm as NaN); ``h_next``: the
        next proposed step, at most ``dt_max``.
        """
        norm = error_norm(y_error, y0, y1_candidate, self.rtol, charge)
        # a non-finite y1 fails this too: its states enter the norm (NaN), and an infinite
        # state gives a NaN vector field, hence a NaN error estimate (no separate finite
        # check: that was ~9 % of a lane-step)
        ok = norm <= 1.0
        accept = active & ok
        factor = jnp.clip(self.safety * _power(jnp.where(norm > 0, norm, 1e-10), self.exponent),
                          self.factormin, self.factormax)
        factor = jnp.where(jnp.isfinite(norm), factor, self.factormin)
        h_next = jnp.where(accept & clipped, jnp.maximum(h_prev, h * factor), h * factor)
        h_next = jnp.where(active, jnp.minimum(h_next, self.dt_max), h_prev)
        return accept, ok, h_next


def _power(x: Array, exponent: float) -> Array:
    """``x ** exponent`` for ``x > 0``; ``-1/4`` as ``rsqrt(sqrt(x))``: XLA compiles a
    general power to ``exp(exponent log x)``, and in the lane step that one power cost
    about as much as a vector-field evaluation's largest kernel (``bench/NOTES.md``)."""
    if exponent == -0.25:
        return jax.lax.rsqrt(jnp.sqrt(x))
    return x ** exponent
