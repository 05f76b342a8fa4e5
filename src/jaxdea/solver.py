"""An exponential (Lawson) Runge-Kutta solver for semilinear stiff systems, as a diffrax solver.

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
integrating-factor (Lawson) form. Constant forcing is integrated exactly because it sits in
``y*``: a resting, charged capacitor is a fixed point of the step (no drift of the steady
voltage, unlike plain Lawson with the source in ``N``).

Piecewise-constant drives: the vector field is sampled strictly inside each step (the stage
times 0 and h are nudged inwards by 1e-9 h) and the linearisation at the step midpoint, so a
square-wave edge that sits on a step boundary belongs to the correct side. Put edges on step
boundaries (``diffrax.StepTo``; :mod:`jaxdea.protocol` clips its adaptive steps to them).
"""

from __future__ import annotations

import abc
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
        h = t1 - t0
        ta = t0 + _NUDGE * h
        tm = t0 + 0.5 * h
        tb = t1 - _NUDGE * h
        lin = _unwrap(terms).linearisation(tm, y0, args)
        ystar = lin.fixed_point

        def remainder(t, z):
            y = _add(ystar, z)
            return _sub(terms.vf(t, y, args), lin.apply(z))

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


def exp_decay_weights(rate, h):
    """``(exp(-rate h), 1 - exp(-rate h))`` computed without cancellation for small rate h."""
    decay = jnp.exp(-rate * h)
    return decay, -jnp.expm1(-rate * h)
