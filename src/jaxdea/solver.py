"""Exponential Runge-Kutta solvers for semilinear stiff systems, as diffrax solvers.

:class:`LawsonRK4` (integrating factor: the engine's, the trajectories' and the calibration
predictors' solver) and :class:`ExponentialRK4` (Krogstad's ETDRK4: ~2x more accurate at
the same tolerance, a step ~1.2x dearer; the engine's with ``StepControl(solver=
"exponential")``).

Why: the RC charge equation of a DEA, ``dQ/dt = (Phi_in - Q/C(d)) / (2 R_s)``, relaxes in
``2 R_s C`` ~ 49 us, while the mechanics moves on the millisecond scale. Explicit RK4 is
unstable above dt ~ 136 us (shared reference performance.md) and needs ~200 steps per cycle to get
P_in right; implicit solvers pay a Newton solve per stage. This solver integrates the stiff
part exactly instead, so the step is set by the mechanics.

The model supplies, at the start of each step, an affine approximation of its stiff part
frozen over the step::

    y' = A (y - y*) + N(t, y),        N(t, y) := f(t, y) - A (y - y*)

(:class:`Linearisation`: ``y*`` is the fixed point of the frozen affine part, ``A`` its
matrix, ``exp(hA)`` its flow). The remainder ``N`` is non-stiff (for the cone: the change of
``C`` with the deflection within one step), and is handled by classical RK4 in the
integrating-factor (Lawson) form by :class:`LawsonRK4`, and against the exact kernel
``exp((h - s) A)`` by :class:`ExponentialRK4`. Constant forcing is integrated exactly
because it sits in ``y*``: a resting, charged capacitor is a fixed point of the step (no
drift of the steady voltage, unlike plain Lawson with the source in ``N``).

Piecewise-constant drives: the vector field is sampled strictly inside each step (the stage
times 0 and h are nudged inwards by 1e-9 h) and the linearisation at the step midpoint, so a
square-wave edge that sits on a step boundary belongs to the correct side. Put edges on step
boundaries (``diffrax.StepTo``; :mod:`jaxdea.protocol` clips its adaptive steps to them).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from typing import ClassVar

import diffrax
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import PyTree

_NUDGE = 1e-9


class Linearisation(eqx.Module):
    """A frozen affine part ``A (y - y*)`` of a vector field, with its exact flow."""

    @property
    @abc.abstractmethod
    def fixed_point(self) -> PyTree:
        """``y*``: where the frozen affine part vanishes (zeros where A is zero)."""

    @abc.abstractmethod
    def apply(self, z: PyTree) -> PyTree:
        """``A z``."""

    @abc.abstractmethod
    def flow(self, h, z: PyTree) -> PyTree:
        """``exp(h A) z``."""

    def phi_k(self, k: int, h, z: PyTree) -> PyTree:
        """``phi_k(h A) z`` (:func:`phi_functions`; ``phi_0 = exp``, :meth:`flow`), which
        :class:`ExponentialRK4` needs. A linearisation that only serves :class:`LawsonRK4`
        need not implement it."""
        raise NotImplementedError(f"{type(self).__name__} has no phi_k(k, h, z): "
                                  "ExponentialRK4 needs it (use LawsonRK4)")


class SemilinearTerm(diffrax.AbstractTerm):
    """An ODE term ``f(t, y, args) dt`` that also offers a stiff linearisation.

    ``linearisation(t, y, args) -> Linearisation``. Any diffrax ODE solver can use this term
    (it behaves as an ``ODETerm``); :class:`LawsonRK4` also uses the linearisation.
    """

    vector_field: Callable
    linearisation: Callable

    def vf(self, t, y, args):
        return self.vector_field(t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jtu.tree_map(lambda v: control * v, vf)


def _unwrap(term):
    """The user's :class:`SemilinearTerm` inside diffrax's wrappers (``WrapTerm``).

    diffeqsolve only integrates forward here (t1 > t0), so the wrapper's direction is +1.
    """
    while not isinstance(term, SemilinearTerm) and hasattr(term, "term"):
        term = term.term
    return term


def _axpy(a, x, y):
    # ``a`` (a step length, f64) in each leaf's own dtype: single-precision states stay single
    return jtu.tree_map(lambda xi, yi: jnp.asarray(a, xi.dtype) * xi + yi, x, y)


def _add(*trees):
    return jtu.tree_map(lambda *xs: sum(xs[1:], xs[0]), *trees)


def _sub(x, y):
    return jtu.tree_map(lambda a, b: a - b, x, y)


def _frozen(terms, t0, t1, y0, args):
    """What both solvers' steps start from: ``h``, the stage times (0 and h nudged inwards
    by ``_NUDGE h``, the midpoint), the linearisation frozen at the midpoint and ``y0``, its
    fixed point ``y*``, and the remainder ``N(t, z) = f(t, y* + z) - A z``."""
    h = t1 - t0
    tm = t0 + 0.5 * h
    lin = _unwrap(terms).linearisation(tm, y0, args)
    ystar = lin.fixed_point

    def remainder(t, z):
        return _sub(terms.vf(t, _add(ystar, z), args), lin.apply(z))

    return h, (t0 + _NUDGE * h, tm, t1 - _NUDGE * h), lin, ystar, remainder


class LawsonRK4(diffrax.AbstractSolver):
    """Integrating-factor (Lawson) RK4 with an affine shift, 4th order, with an embedded
    3rd-order error estimate (one extra stage) so it works with ``diffrax.PIDController`` as
    well as with fixed steps (``StepTo``, ``ConstantStepSize``). Needs a :class:`SemilinearTerm`.
    """

    term_structure: ClassVar = SemilinearTerm
    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation

    def order(self, terms):
        return 4

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        h, (ta, tm, tb), lin, ystar, remainder = _frozen(terms, t0, t1, y0, args)

        z0 = _sub(y0, ystar)
        e_half = lambda z: lin.flow(0.5 * h, z)  # noqa: E731
        e_full = lambda z: lin.flow(h, z)  # noqa: E731
        k1 = remainder(ta, z0)
        k2 = remainder(tm, e_half(_axpy(0.5 * h, k1, z0)))
        k3 = remainder(tm, _axpy(0.5 * h, k2, e_half(z0)))
        k4 = remainder(tb, _axpy(h, e_half(k3), e_full(z0)))
        incr = _add(e_full(k1), jtu.tree_map(lambda a: 2.0 * a, e_half(_add(k2, k3))), k4)
        z1 = _axpy(h / 6.0, incr, e_full(z0))
        y1 = _add(ystar, z1)
        # Embedded 3rd-order solution with the extra stage k5 = N(t1, y1):
        # b_hat = (1/6, 1/3, 1/3, 0, 1/6) => error = h/6 (k4 - k5).
        k5 = remainder(tb, z1)
        y_error = jtu.tree_map(lambda a, b: jnp.asarray(h / 6.0, a.dtype) * (a - b), k4, k5)
        dense_info = dict(y0=y0, y1=y1)
        return y1, y_error, dense_info, None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class ExponentialRK4(LawsonRK4):
    """Krogstad's exponential Runge-Kutta method of order 4 (ETDRK4-K), with the same affine
    shift, stage times and embedded error estimate as :class:`LawsonRK4`. Needs a
    :class:`SemilinearTerm` whose linearisation has :meth:`Linearisation.phi_k`.

    Why: the Lawson form propagates the remainder ``N`` by ``exp(hA)`` as if it were
    constant along the exact flow, so its error carries powers of ``A`` (the RC rate
    ``kappa`` ~ 2e4 /s) and is not seen by the embedded estimate. Measured on DCDEA-LS in the
    on-phase at 43 Hz (steps of 50 / 100 us against a 1000-substep solution, scaled as in
    the step control): the charge's true local error 4.0 / 89 where LawsonRK4's estimate
    says 0.16 / 3.2; this method's 0.05 / 1.2 against its estimate 0.11 / 1.7. Here the
    remainder is integrated against the exact kernel, ``int exp((h - s) A) N(s) ds``, with
    ``N`` interpolated through the stages (the ``phi_k`` functions), so the stiff mode costs
    no accuracy (Krogstad, J. Comput. Phys. 203 (2005) 72-88, the scheme of its section 3;
    Hochbruck & Ostermann, Acta Numerica 19 (2010) 209-286, section 2.3). With ``A = 0`` it
    is classical RK4.

    Stages (``z = y - y*``, ``N_i = N(t_i, Z_i)``, ``phi_k = phi_k(hA)``,
    ``psi_k = phi_k(hA/2)``)::

        Z2 = psi_0 z0 + h/2 psi_1 N1
        Z3 = Z2 + h psi_2 (N2 - N1)
        Z4 = phi_0 z0 + h phi_1 N1 + 2 h phi_2 (N3 - N1)
        z1 = phi_0 z0 + h [(phi_1 - 3 phi_2 + 4 phi_3) N1
                           + (2 phi_2 - 4 phi_3) (N2 + N3) + (4 phi_3 - phi_2) N4]

    Error estimate: ``N5 = N(t1-, z1)`` in place of ``N4`` gives the embedded solution, so
    the error is ``h (4 phi_3 - phi_2) (N4 - N5)`` (``h/6 (N4 - N5)`` at ``A = 0``).
    """

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        h, (ta, tm, tb), lin, ystar, remainder = _frozen(terms, t0, t1, y0, args)

        def combine(*pairs):  # sum over (k, v) of phi_k(hA) v
            return _add(*(lin.phi_k(k, h, v) for k, v in pairs))

        def half(k, v):
            return lin.phi_k(k, 0.5 * h, v)

        z0 = _sub(y0, ystar)
        n1 = remainder(ta, z0)
        z2 = _axpy(0.5 * h, half(1, n1), half(0, z0))
        n2 = remainder(tm, z2)
        z3 = _axpy(h, half(2, _sub(n2, n1)), z2)
        n3 = remainder(tm, z3)
        e0 = lin.flow(h, z0)
        z4 = _axpy(h, combine((1, n1), (2, _scale(2.0, _sub(n3, n1)))), e0)
        n4 = remainder(tb, z4)
        n23 = _add(n2, n3)
        # phi_1 - 3 phi_2 + 4 phi_3 on N1; 2 phi_2 - 4 phi_3 on N2 + N3; 4 phi_3 - phi_2 on N4
        incr = combine((1, n1), (2, _add(_scale(-3.0, n1), _scale(2.0, n23), _scale(-1.0, n4))),
                       (3, _scale(4.0, _add(_sub(n1, n23), n4))))
        z1 = _axpy(h, incr, e0)
        y1 = _add(ystar, z1)
        n5 = remainder(tb, z1)
        d45 = _sub(n4, n5)
        y_error = combine((2, _scale(-h, d45)), (3, _scale(4.0 * h, d45)))
        dense_info = dict(y0=y0, y1=y1)
        return y1, y_error, dense_info, None, diffrax.RESULTS.successful


def phi_functions(a, kmax: int = 3):
    """``(phi_0(a), ..., phi_kmax(a))`` elementwise for real ``a <= 0``: ``phi_0 = exp``,
    ``phi_{k+1}(a) = (phi_k(a) - 1/k!) / a``, ``phi_k(0) = 1/k!``.

    The recurrence from ``phi_1 = expm1(a)/a`` loses about a factor ``1/|a|`` per level, so
    below ``|a| = 0.1`` the Taylor series ``sum_j a^j / (j + k)!`` (10 terms, to ~3e-16) is
    used instead. Computed in ``a``'s dtype (pass float64 for single-precision states).
    """
    small = jnp.abs(a) < 0.1
    safe = jnp.where(small, -1.0, a)
    out = [jnp.exp(a)]
    rec = jnp.expm1(safe) / safe
    for k in range(1, kmax + 1):
        if k > 1:
            rec = (rec - 1.0 / math.factorial(k - 1)) / safe
        series = 0.0
        for j in reversed(range(10)):  # Horner
            series = series * a + 1.0 / math.factorial(j + k)
        out.append(jnp.where(small, series, rec))
    return tuple(out)


def _scale(c, x):
    return jtu.tree_map(lambda a: jnp.asarray(c, a.dtype) * a, x)


def exp_decay_weights(rate, h):
    """``(exp(-rate h), 1 - exp(-rate h))``.

    The second weight is ``1 - exp(-x)``, not ``-expm1(-x)``: XLA's CPU ``expm1`` kept the
    lane step's largest kernel (the input energy's Lawson combination) a scalar loop on one
    device (``bench/NOTES.md``). Its cancellation below ``x ~ 0.1`` is ~1e-16 in absolute
    terms, and the weight multiplies ``Phi z_Q`` into the input-energy accumulator, whose own
    rounding (1e-16 of the energy so far) is larger.
    """
    decay = jnp.exp(-rate * h)
    return decay, 1.0 - decay
