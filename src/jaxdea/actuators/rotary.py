"""Rotational double-cone DEA (paper 003): a rigid spacer between two cone membranes.

Model (paper 003, "System Modeling"):

- structure: rigid spacer ``q = [G_x, G_y, theta]`` with Lagrangian eq 2, so
  ``m G_x'' = tau_Gx``, ``m G_y'' + m g = tau_Gy``, ``I theta'' = tau_theta`` (eqs 3-5);
  gravity is optional (``gravity = 0`` switches it off, as the paper's parameter study does);
- four lumped DE elements A-D (two adjacent segments of one membrane each), lengths from
  the kinematics of eqs 16-24 (:func:`jaxdea.geometry.double_cone_lengths`);
- normalisation eq 7 (stretch), eq 8 (stress, in its dimensionally consistent reading, see
  below) and eq 9 (field), the Ogden-type law with viscous term of eq 10
  (:func:`jaxdea.materials.ogden_type_stress`);
- Jacobian ``J = dl/dq`` (eq 26) by ``jax.jacfwd``, generalized forces ``tau = -J^T f``
  (eq 28), stretch rate from ``l' = J q'`` (eq 29);
- drive voltage eq 30 (the field is ``E_max`` at ``q = 0``), any pattern of the four elements.

Readings (see ``docs/models.md`` and the shared ``reference/rotary.md``):

- eq 8 as printed, ``sigma = 2 lam f / (pi z0 (r_o^2 - r_i^2))``, is one length off; we use
  ``f = sigma pi z0 (r_o + r_i) / (2 lam)`` (half the mean circumference times the current
  thickness ``z0 / lam``). Without gravity the force scale (and z0) drop out of the angle.
- ``field="frozen"`` (default) evaluates eq 9 with the stretch at ``q = 0``, so an element at
  the eq-30 voltage always sees ``E_max``: this reproduces the paper's model numbers.
  ``field="literal"`` uses the current stretch (larger angles, e.g. 11.2 instead of 9.8 deg).

Steady state: :func:`equilibrium` (Newton with voltage continuation from the unactuated state,
stability from the stiffness eigenvalues) and :func:`settle` (diffrax to rest) agree;
:func:`steady_angle` is differentiable by the implicit function theorem; :func:`rotary_study`
maps the angle over ``(r_i, d)`` in one vmapped, jitted call (paper 003 Fig 12);
:func:`optimise_design` maximises it by gradient (L-BFGS-B with JAX gradients).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ..config import ConfigError, Field, _section
from ..geometry import double_cone_lengths
from ..materials import EPS0, ogden_type_stress

#: Status codes of an equilibrium / study cell.
ROTARY_STATUS = {
    0: "ok: stable equilibrium reached by voltage continuation",
    1: "no stable equilibrium: the continuation path lost stability (stiffness eigenvalue <= 0)",
    2: "not converged: Newton did not converge on the continuation path",
    3: "invalid geometry: needs 0 < r_i < r_o, d + f > h, z0 > 0",
}
OK, UNSTABLE, NOT_CONVERGED, INVALID = 0, 1, 2, 3

ELEMENTS = ("A", "B", "C", "D")
FIELD_MODES = ("frozen", "literal")


class OgdenTypeDE(eqx.Module):
    """Material of the lumped DE elements (paper 003 eq 10, Table 1).

    ``alpha`` (-): tuple of the N exponents, static (structural, like the order N: integer
    exponents then cost products, not ``pow``); ``beta`` (Pa), ``gamma`` (Pa): arrays of
    shape ``(N,)`` of the modified N-th order Ogden law; ``eps_r`` relative permittivity;
    ``eta_v0`` viscous coefficient (Pa s).
    """

    alpha: tuple = eqx.field(static=True)
    beta: Array
    gamma: Array
    eps_r: Array
    eta_v0: Array

    def stress(self, lam: ArrayLike, lam_dot: ArrayLike, field: ArrayLike) -> Array:
        """True radial stress (Pa) at stretch ``lam``, rate ``lam_dot`` (1/s), field (V/m)."""
        return ogden_type_stress(lam, lam_dot, field, self.alpha, self.beta, self.gamma,
                                 EPS0 * self.eps_r, self.eta_v0)


class FilteredStep(eqx.Module):
    """Low-pass filtered step voltage, ``v(t) = v_final (1 - exp(-t / tau))`` for t >= 0.

    The paper uses "a low-pass filtered step" without giving the filter; a first-order
    filter with time constant ``tau`` (s) is our choice. ``v_final`` has shape ``(4,)`` (A-D).
    """

    v_final: Array
    tau: Array

    def __call__(self, t: ArrayLike) -> Array:
        t = jnp.maximum(jnp.asarray(t), 0.0)
        return self.v_final * (-jnp.expm1(-t / self.tau))


class RotaryDCDEA(eqx.Module):
    """3-DOF rotational double-cone DEA of paper 003 (SI units; all fields are pytree leaves
    except ``field`` and the material's exponents ``alpha``).

    Geometry (Fig 5D): ``r_i``, ``r_o`` inner/outer membrane radius, ``d`` half spacer length,
    ``f`` half thickness of the spacer's inner frame, ``h`` half thickness of the outer frame,
    ``z0`` undeformed membrane thickness (m). Spacer: ``mass`` (kg), ``inertia`` (kg m^2),
    ``gravity`` (m/s^2, 0 = off). Drive: ``field_max`` (V/m, eq 30), ``pattern`` (4,)
    multipliers of the eq-30 voltage for elements A-D (default B + C, theta > 0),
    ``filter_time`` (s) of the filtered step. ``field``: "frozen" or "literal" eq 9.
    """

    r_i: Array
    r_o: Array
    d: Array
    f: Array
    h: Array
    z0: Array
    mass: Array
    inertia: Array
    gravity: Array
    material: OgdenTypeDE
    field_max: Array
    pattern: Array
    filter_time: Array
    field: str = eqx.field(static=True, default="frozen")

    # ---- kinematics (eqs 7, 16-24, 26, 29) ----------------------------------------------

    def lengths(self, q: ArrayLike) -> Array:
        """``l_DE(q)``, shape (4,), m (eqs 16-24)."""
        return double_cone_lengths(q, self.r_i, self.r_o, self.d, self.f, self.h)

    def jacobian(self, q: ArrayLike) -> Array:
        """``J(q) = dl_DE/dq``, shape (4, 3) (eq 26), by forward-mode autodiff."""
        return jax.jacfwd(self.lengths)(jnp.asarray(q, dtype=jnp.float64))

    def stretches(self, q: ArrayLike) -> Array:
        """Radial stretches ``lam = l / (r_o - r_i)`` (eq 7)."""
        return self.lengths(q) / (self.r_o - self.r_i)

    def rest_stretch(self) -> Array:
        """Stretch of every element at ``q = 0``: ``sqrt(1 + ((d + f - h) / (r_o - r_i))^2)``."""
        return jnp.sqrt(1.0 + ((self.d + self.f - self.h) / (self.r_o - self.r_i)) ** 2)

    # ---- electrical (eqs 9, 30) ---------------------------------------------------------

    def voltage_max(self) -> Array:
        """Eq 30: the voltage giving ``field_max`` at ``q = 0``, ``z0 E_max / lam(q=0)`` (V)."""
        return self.z0 * self.field_max / self.rest_stretch()

    def voltages(self, scale: ArrayLike = 1.0) -> Array:
        """Element voltages (4,) of the activation pattern at ``scale`` times eq 30 (V)."""
        return scale * self.pattern * self.voltage_max()

    def electric_field(self, lam: ArrayLike, v: ArrayLike) -> Array:
        """Eq 9, ``E = lam v / z0``; with ``field="frozen"`` ``lam`` is the stretch at q = 0."""
        if self.field == "frozen":
            lam = self.rest_stretch()
        return lam * jnp.asarray(v) / self.z0

    # ---- forces (eqs 8, 10, 28) ---------------------------------------------------------

    def _forces_from(self, lengths: Array, lengths_dot: Array | float, v: ArrayLike) -> Array:
        """Eq 7 -> eq 10 -> eq 8: element forces from lengths, their rates and voltages."""
        span = self.r_o - self.r_i
        lam = lengths / span
        sigma = self.material.stress(lam, lengths_dot / span, self.electric_field(lam, v))
        return sigma * math.pi * self.z0 * (self.r_o + self.r_i) / (2.0 * lam)

    def element_forces(self, q: ArrayLike, qdot: ArrayLike, v: ArrayLike) -> Array:
        """Tensile forces ``f_DE`` (4,) in N: eq 10 stress turned into force by eq 8 read as
        ``f = sigma pi z0 (r_o + r_i) / (2 lam)`` (dimensionally consistent form); the
        stretch rate from ``l' = J q'`` (eq 29)."""
        q = jnp.asarray(q, dtype=jnp.float64)
        return self._forces_from(self.lengths(q), self.jacobian(q) @ jnp.asarray(qdot), v)

    def generalized_forces(self, q: ArrayLike, qdot: ArrayLike, v: ArrayLike) -> Array:
        """``tau = -J(q)^T f_DE`` (eq 28), ``[N, N, N m]``."""
        q = jnp.asarray(q, dtype=jnp.float64)
        lengths, jac = self.lengths(q), self.jacobian(q)
        return -jac.T @ self._forces_from(lengths, jac @ jnp.asarray(qdot), v)

    def static_residual(self, q: ArrayLike, v: ArrayLike) -> Array:
        """Net generalized force at rest: ``tau(q, 0, v) - [0, m g, 0]`` (eqs 3-5 with q'' = 0)."""
        q = jnp.asarray(q, dtype=jnp.float64)
        return -self.jacobian(q).T @ self._forces_from(self.lengths(q), 0.0, v) - self._weight()

    def _weight(self) -> Array:
        """Gravity's generalized force ``[0, m g, 0]`` (eq 4)."""
        return jnp.stack([0.0 * self.mass, self.mass * self.gravity, 0.0 * self.mass])

    def mass_matrix_diag(self) -> Array:
        return jnp.stack([self.mass, self.mass, self.inertia])

    # ---- DESIGN interface ---------------------------------------------------------------

    def initial_state(self) -> Array:
        """``[q, q']`` at the unactuated static equilibrium (solved: gravity makes it sag)."""
        q0 = equilibrium(self, jnp.zeros(4)).q
        return jnp.concatenate([q0, jnp.zeros(3)])

    def vector_field(self, t, y, args) -> Array:
        """Eqs 3-5 as a first-order system; ``args`` is the drive, ``t -> v (4,)``."""
        q, qdot = y[:3], y[3:]
        tau = self.generalized_forces(q, qdot, args(t)) - self._weight()
        return jnp.concatenate([qdot, tau / self.mass_matrix_diag()])

    def observables(self, t, y, args) -> dict:
        q, qdot = y[:3], y[3:]
        v = args(t)
        lam = self.stretches(q)
        return {"G_x": q[0], "G_y": q[1], "theta": q[2], "stretch": lam,
                "force": self.element_forces(q, qdot, v), "voltage": v,
                "field": self.electric_field(lam, v)}

    def drive(self) -> FilteredStep:
        """The paper's filtered step to the eq-30 voltage on the pattern's elements."""
        return FilteredStep(self.voltages(), self.filter_time)

    # ---- helpers ------------------------------------------------------------------------

    def valid_geometry(self) -> Array:
        """True where ``0 < r_i < r_o``, ``d + f > h`` and ``z0 > 0`` (cone neither flat nor
        inverted)."""
        return (self.r_i > 0) & (self.r_i < self.r_o) & (self.d + self.f > self.h) & (self.z0 > 0)

    def with_geometry(self, r_i: ArrayLike | None = None, d: ArrayLike | None = None
                      ) -> "RotaryDCDEA":
        """Copy with a new inner radius and/or half spacer length (m)."""
        out = self
        if r_i is not None:
            out = eqx.tree_at(lambda m: m.r_i, out, jnp.asarray(r_i, dtype=jnp.float64))
        if d is not None:
            out = eqx.tree_at(lambda m: m.d, out, jnp.asarray(d, dtype=jnp.float64))
        return out

    def with_pattern(self, pattern: ArrayLike) -> "RotaryDCDEA":
        """Copy with another activation pattern (4 multipliers of the eq-30 voltage, A-D)."""
        return eqx.tree_at(lambda m: m.pattern, self, jnp.asarray(pattern, dtype=jnp.float64))

    def with_field(self, field: str) -> "RotaryDCDEA":
        """Copy with the other eq-9 reading ("frozen" or "literal")."""
        if field not in FIELD_MODES:
            raise ConfigError(f"field = {field!r} is not one of {', '.join(FIELD_MODES)}")
        return _replace_static(self, field)


def _replace_static(model: RotaryDCDEA, field: str) -> RotaryDCDEA:
    kw = {k: getattr(model, k) for k in model.__dataclass_fields__}
    kw["field"] = field
    return RotaryDCDEA(**kw)


def _f64(x) -> Array:
    return jnp.asarray(x, dtype=jnp.float64)


def paper_model(r_i: float = 2e-3, d: float = 7e-3, *, gravity: float = 0.0,
                field: str = "frozen", pattern=(0.0, 1.0, 1.0, 0.0), mass: float = 5e-3,
                inertia: float = 1e-6, z0: float = 50e-6, filter_time: float = 0.05,
                check: bool = True) -> RotaryDCDEA:
    """Table 1 of paper 003 with the given ``r_i``, ``d`` (m); the rest as in
    ``configs/rotary_dcdea.toml``. ``check`` raises :class:`ConfigError` on invalid geometry."""
    model = RotaryDCDEA(
        r_i=_f64(r_i), r_o=_f64(22.5e-3), d=_f64(d), f=_f64(0.0), h=_f64(2e-3), z0=_f64(z0),
        mass=_f64(mass), inertia=_f64(inertia), gravity=_f64(gravity),
        material=OgdenTypeDE(alpha=(2.0, 4.0), beta=_f64([1.707e6, -0.023e6]),
                             gamma=_f64([1.298e6, -0.955e6]), eps_r=_f64(2.8),
                             eta_v0=_f64(0.2e6)),
        field_max=_f64(80e6), pattern=_f64(pattern), filter_time=_f64(filter_time),
        field=field,
    )
    if field not in FIELD_MODES:
        raise ConfigError(f"field = {field!r} is not one of {', '.join(FIELD_MODES)}")
    if check:
        check_geometry(model)
    return model


def check_geometry(model: RotaryDCDEA, prefix: str = "geometry") -> None:
    """Raise :class:`ConfigError` naming the field and its allowed range when the geometry is
    outside the model's validity (needs concrete values)."""
    r_i, r_o, d, f, h, z0 = (float(getattr(model, k)) for k in ("r_i", "r_o", "d", "f", "h", "z0"))
    if not z0 > 0:
        raise ConfigError(f"{prefix}.thickness = {z0:g} m is outside the allowed range (0, inf) m")
    if not 0 < r_i < r_o:
        raise ConfigError(f"{prefix}.inner_radius = {r_i:g} m is outside the allowed range "
                          f"(0, {r_o:g}) m: it must be below {prefix}.outer_radius")
    if not d + f > h:
        raise ConfigError(
            f"{prefix}.spacer_half_length = {d:g} m is outside the allowed range ({h - f:g}, inf)"
            f" m: d + f must exceed h = {h:g} m, or the cones are flat or inverted")


# ---- static equilibrium -------------------------------------------------------------------


def _scales(model: RotaryDCDEA) -> Array:
    """Variable scales ``[L, L, 1]`` (L = r_o - r_i) for convergence tests and stiffness."""
    span = model.r_o - model.r_i
    return jnp.stack([span, span, jnp.ones_like(span)])


def _residual_and_jacobian(model: RotaryDCDEA, q: Array, v: Array) -> tuple[Array, Array]:
    """Static residual and its Jacobian ``dR/dq`` (forward-mode autodiff)."""
    return model.static_residual(q, v), jax.jacfwd(model.static_residual)(q, v)


def _scaled_sym(model: RotaryDCDEA, dres: Array) -> Array:
    """Stiffness ``-dR/dq`` scaled to ``[G/L, G/L, theta]`` and symmetrised."""
    scale = _scales(model)
    ks = -dres * scale[:, None] * scale[None, :]
    return 0.5 * (ks + ks.T)


def _solve3(a: Array, b: Array) -> Array:
    """``a^-1 b`` for a 3x3 ``a`` by Cramer's rule (much faster than LAPACK under vmap on CPU)."""
    c0 = jnp.cross(a[1], a[2])
    c1 = jnp.cross(a[2], a[0])
    c2 = jnp.cross(a[0], a[1])
    det = jnp.dot(a[0], c0)
    return (b[0] * c0 + b[1] * c1 + b[2] * c2) / det


def min_eig_sym3(k: Array) -> Array:
    """Smallest eigenvalue of a symmetric 3x3 matrix (closed form, trigonometric method)."""
    p1 = k[0, 1] ** 2 + k[0, 2] ** 2 + k[1, 2] ** 2
    tr = k[0, 0] + k[1, 1] + k[2, 2]
    mean = tr / 3.0
    p2 = (k[0, 0] - mean) ** 2 + (k[1, 1] - mean) ** 2 + (k[2, 2] - mean) ** 2 + 2.0 * p1
    p = jnp.sqrt(p2 / 6.0)
    p_safe = jnp.where(p > 0, p, 1.0)
    b = (k - mean * jnp.eye(3)) / p_safe
    r = jnp.clip(_det3(b) / 2.0, -1.0, 1.0)
    phi = jnp.arccos(r) / 3.0
    return jnp.where(p > 0, mean + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0), mean)


def _det3(a: Array) -> Array:
    return jnp.dot(a[0], jnp.cross(a[1], a[2]))


def stiffness(model: RotaryDCDEA, q: ArrayLike, v: ArrayLike) -> Array:
    """Stiffness ``K = -d(residual)/dq`` in scaled coordinates ``[G/L, G/L, theta]``
    (symmetric: the static forces derive from a potential); stable iff all eigenvalues > 0."""
    q = jnp.asarray(q, dtype=jnp.float64)
    return _scaled_sym(model, jax.jacfwd(model.static_residual)(q, jnp.asarray(v)))


class Equilibrium(NamedTuple):
    """Result of :func:`equilibrium`: ``q`` (3,), ``status`` (see ``ROTARY_STATUS``),
    ``min_eig`` smallest scaled stiffness eigenvalue on the path (N m), ``step`` last Newton
    step (scaled)."""

    q: Array
    status: Array
    min_eig: Array
    step: Array


def equilibrium(model: RotaryDCDEA, v: ArrayLike | None = None, *, steps: int = 3,
                iters: int = 4, final_iters: int = 2, rest_iters: int = 4,
                tol: float = 1e-9) -> Equilibrium:
    """Stable static equilibrium under voltages ``v`` (4,) (default: the pattern at eq 30),
    reached by continuation in ``v^2`` from the unactuated equilibrium.

    ``rest_iters`` Newton iterations at 0 V (the unactuated state sags under gravity), then
    ``steps`` continuation steps of ``iters`` iterations each, then ``final_iters`` more at
    full voltage, all in ONE scan over a voltage schedule (one loop body to compile);
    converged when the last scaled step is below ``tol``. Stability: at the end of every
    stage the (converged) stiffness must be positive definite (smallest eigenvalue of the
    scaled, symmetric stiffness, closed form); otherwise status 1: the stable branch reached
    from the unactuated state ended in a fold, so there is no stable equilibrium connected
    to it. Pure JAX: vmaps and jits. Invalid geometry gives status 3; q is NaN unless status 0.
    """
    v = model.voltages() if v is None else jnp.asarray(v, dtype=jnp.float64)
    return _equilibrium(model, v, steps=steps, iters=iters, final_iters=final_iters,
                        rest_iters=rest_iters, tol=tol)


@eqx.filter_jit
def _equilibrium(model: RotaryDCDEA, v: Array, *, steps: int, iters: int, final_iters: int,
                 rest_iters: int, tol: float) -> Equilibrium:
    valid = model.valid_geometry()
    # keep the arithmetic finite where the geometry is invalid (masked at the end)
    safe = eqx.tree_at(lambda m: (m.r_i, m.d, m.z0), model,
                       (jnp.where(valid, model.r_i, 0.5 * model.r_o),
                        jnp.where(valid, model.d, model.h - model.f + 1e-3),
                        jnp.where(valid, model.z0, 1e-5)))
    fractions = np.sqrt(np.arange(1, steps + 1) / steps)  # linear in v^2 (Maxwell stress)
    stages = [np.zeros(rest_iters)] + [np.full(iters, s) for s in fractions] \
        + [np.ones(final_iters)]
    ends = np.concatenate([np.arange(len(st)) == len(st) - 1 for st in stages])
    schedule = np.concatenate(stages)
    scale = _scales(safe)

    def body(q, inp):
        frac, end = inp
        r, k = _residual_and_jacobian(safe, q, frac * v)
        eig = min_eig_sym3(_scaled_sym(safe, k))
        dq = -_solve3(k, r)
        big = jnp.max(jnp.abs(dq / scale))
        dq = jnp.where(big > 0.1, dq * 0.1 / big, dq)  # limit steps to 0.1 rad / 0.1 L
        ok = jnp.all(jnp.isfinite(dq))
        q = q + jnp.where(ok, dq, 0.0)
        big = jnp.where(ok, big, jnp.inf)
        # the stiffness counts where a stage ends on a converged iterate
        return q, (big, jnp.where(end & (big < 1e-4), eig, jnp.inf))

    q, (bigs, eigs) = jax.lax.scan(body, jnp.zeros(3), (jnp.asarray(schedule),
                                                         jnp.asarray(ends)))
    step = bigs[-1]
    converged = (step < tol) & jnp.all(jnp.isfinite(q))
    min_eig = jnp.min(eigs)
    status = jnp.where(~valid, INVALID,
                       jnp.where(min_eig <= 0, UNSTABLE,
                                 jnp.where(converged, OK, NOT_CONVERGED)))
    q = jnp.where(status == OK, q, jnp.nan)
    return Equilibrium(q=q, status=status.astype(jnp.int32), min_eig=min_eig, step=step)


def _no_grad(tree):
    return jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


def equilibrium_q(model: RotaryDCDEA, v: ArrayLike | None = None, **kw) -> tuple[Array, Array]:
    """``(q, status)`` of :func:`equilibrium`, differentiable in the model parameters by the
    implicit function theorem: ``dq/dp = -(dR/dq)^-1 dR/dp`` at the solution ``R(q, p) = 0``
    (one Newton step with a frozen Jacobian: its value is ``q``, its derivative the IFT one)."""
    vv = model.voltages() if v is None else jnp.asarray(v, dtype=jnp.float64)
    sol = equilibrium(_no_grad(model), jax.lax.stop_gradient(vv), **kw)
    q_star = jax.lax.stop_gradient(sol.q)
    kq = jax.lax.stop_gradient(jax.jacfwd(model.static_residual)(q_star, vv))
    q = q_star - _solve3(kq, model.static_residual(q_star, vv))
    return q, sol.status


def steady_angle(model: RotaryDCDEA, v: ArrayLike | None = None, **kw) -> Array:
    """Steady rotation angle theta (rad) of the stable equilibrium (NaN unless status 0);
    differentiable (IFT) for ``jax.grad`` w.r.t. any model parameter, e.g. ``r_i`` and ``d``."""
    return equilibrium_q(model, v, **kw)[0][2]


# ---- time integration (diffrax) -----------------------------------------------------------


def _rest_event(tol: float, t_min):
    """Event: at rest when ``t > t_min`` and every scaled velocity ``|G'/L|, |theta'|`` is
    below ``tol`` (1/s). (diffrax's ``steady_state_event`` fires at t = 0, where the
    unactuated spacer is at rest before the drive rises.)"""

    def cond_fn(t, y, args, **kwargs):
        model = args[1]
        vel = jnp.abs(y[3:] / _scales(model))
        return (t > t_min) & (jnp.max(vel) < tol)

    return diffrax.Event(cond_fn)


@eqx.filter_jit
def _integrate(model: RotaryDCDEA, drive, y0, t_end, ts, rtol, atol, rest_tol, t_min,
               max_steps: int = 200_000):
    """diffrax Tsit5 with a PID controller (the system is overdamped but only mildly stiff:
    an explicit solver compiles in seconds where an implicit one takes tens; all numbers are
    passed as arrays so new values do not recompile). Saves at ``ts``
    and at the end; stops early at rest (:func:`_rest_event`; ``rest_tol = 0`` never fires).
    One compiled function serves :func:`simulate_rotary` and :func:`settle`."""
    term = diffrax.ODETerm(lambda t, y, args: args[1].vector_field(t, y, args[0]))
    sol = diffrax.diffeqsolve(
        term, diffrax.Tsit5(), t0=0.0, t1=t_end, dt0=1e-5, y0=y0, args=(drive, model),
        saveat=diffrax.SaveAt(ts=ts, t1=True),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps, event=_rest_event(rest_tol, t_min), throw=False,
    )
    return sol.ts, sol.ys, sol.result, sol.stats["num_steps"]


def simulate_rotary(model: RotaryDCDEA, t_end: float = 1.0, n_save: int = 401, drive=None,
                    rtol: float = 1e-8, atol: float = 1e-12):
    """Dynamic response (paper 003 eqs 3-5 with eq 10's viscous term) to ``drive`` (default:
    the filtered step to the eq-30 voltage, :class:`FilteredStep`) from the unactuated
    equilibrium.

    Returns an ``xarray.Dataset`` over ``t`` (s): ``theta_deg``, ``G_x``, ``G_y`` (m) and per
    element ``stretch``, ``force`` (N), ``voltage`` (V), ``field`` (V/m).
    """
    import xarray as xr

    drive = model.drive() if drive is None else drive
    ts = jnp.linspace(0.0, t_end, n_save)  # n_save = 401 shares settle's compilation
    ts_out, ys, result, _ = _integrate(model, drive, model.initial_state(), *map(
        _f64, (t_end, ts, rtol, atol, 0.0, 0.0)))
    if not bool(result == diffrax.RESULTS.successful):
        raise RuntimeError(f"diffrax failed: {result}")
    ts_out, ys = ts_out[:-1], ys[:-1]  # drop the t1 copy
    obs = _observe(model, drive, ts_out, ys)
    el = ("t", "element")
    return xr.Dataset(
        {
            "theta_deg": (("t",), np.degrees(np.asarray(obs["theta"])), {"units": "deg"}),
            "G_x": (("t",), np.asarray(obs["G_x"]), {"units": "m"}),
            "G_y": (("t",), np.asarray(obs["G_y"]), {"units": "m"}),
            "stretch": (el, np.asarray(obs["stretch"]), {"units": "1"}),
            "force": (el, np.asarray(obs["force"]), {"units": "N"}),
            "voltage": (el, np.asarray(obs["voltage"]), {"units": "V"}),
            "field": (el, np.asarray(obs["field"]), {"units": "V/m"}),
        },
        coords={"t": ("t", np.asarray(ts_out), {"units": "s"}), "element": list(ELEMENTS)},
        attrs={"r_i": float(model.r_i), "d": float(model.d), "field_mode": model.field},
    )


@eqx.filter_jit
def _observe(model: RotaryDCDEA, drive, ts, ys) -> dict:
    return jax.vmap(lambda t, y: model.observables(t, y, drive))(ts, ys)


class Settled(NamedTuple):
    """Result of :func:`settle`: final ``q`` (3,), time at rest ``t`` (s), solver steps."""

    q: Array
    t: Array
    steps: Array


def settle(model: RotaryDCDEA, drive=None, t_end: float = 30.0, rtol: float = 1e-10,
           atol: float = 1e-14, rest_tol: float = 1e-9, n_save: int = 401) -> Settled:
    """Integrate the dynamics (diffrax) from the unactuated equilibrium until rest: after
    ``3 filter_time``, every scaled velocity below ``rest_tol`` 1/s (with the ~0.2 s slowest
    time constant of Table 1 that leaves ~1e-10 rad of motion to go)."""
    drive = model.drive() if drive is None else drive
    t_min = 3.0 * getattr(drive, "tau", 0.0)
    grid = jnp.linspace(0.0, t_end, n_save)  # same shape as simulate_rotary: one compilation
    ts, ys, result, steps = _integrate(model, drive, model.initial_state(), *map(
        _f64, (t_end, grid, rtol, atol, rest_tol, t_min)))
    if not bool(result == diffrax.RESULTS.event_occurred):
        raise RuntimeError(f"diffrax did not reach rest by t = {t_end} s: {result}")
    last = int(jnp.sum(jnp.isfinite(ts))) - 1  # saves after the event are inf; t1 = event
    return Settled(q=ys[last, :3], t=ts[last], steps=steps)


# ---- batched (r_i, d) study (paper 003 Fig 12) ----------------------------------------------


@eqx.filter_jit
def _study_kernel(model: RotaryDCDEA, ri: Array, d: Array):
    def cell(r, dd):
        m = model.with_geometry(r, dd)
        sol = equilibrium(m)
        return sol.q[2], sol.status, m.voltage_max(), m.rest_stretch(), sol.min_eig

    return jax.vmap(cell)(ri, d)


def rotary_study(model: RotaryDCDEA, ri: ArrayLike, d: ArrayLike):
    """Steady angle over the grid ``ri x d`` (m) in ONE vmapped, jitted call.

    Each cell uses its own eq-30 voltage on the model's activation pattern. Returns an
    ``xarray.Dataset`` with dims ``(ri, d)``: ``theta_deg`` (NaN unless ``status == 0``),
    ``status`` (codes in ``attrs['status_codes']``), ``voltage`` (V), ``rest_stretch``,
    ``min_stiffness_eig``.
    """
    import xarray as xr

    ri = np.atleast_1d(np.asarray(ri, dtype=np.float64))
    d = np.atleast_1d(np.asarray(d, dtype=np.float64))
    if ri.ndim != 1 or d.ndim != 1:
        raise ValueError("ri and d must be 1-D arrays of metres")
    RI, D = np.meshgrid(ri, d, indexing="ij")
    theta, status, volt, lam0, eig = _study_kernel(model, jnp.asarray(RI.ravel()),
                                                   jnp.asarray(D.ravel()))
    shape = RI.shape
    dims = ("ri", "d")
    status = np.asarray(status).reshape(shape)
    theta = np.where(status == 0, np.degrees(np.asarray(theta)).reshape(shape), np.nan)
    valid = status != INVALID
    return xr.Dataset(
        {
            "theta_deg": (dims, theta, {"units": "deg", "long_name": "steady rotation angle"}),
            "status": (dims, status.astype(np.int32)),
            "voltage": (dims, np.where(valid, np.asarray(volt).reshape(shape), np.nan),
                        {"units": "V", "long_name": "eq-30 voltage"}),
            "rest_stretch": (dims, np.where(valid, np.asarray(lam0).reshape(shape), np.nan),
                             {"units": "1"}),
            "min_stiffness_eig": (dims, np.asarray(eig).reshape(shape), {"units": "N m"}),
        },
        coords={"ri": ("ri", ri, {"units": "m"}), "d": ("d", d, {"units": "m"})},
        attrs={"model": "rotary_dcdea", "field_mode": model.field,
               "pattern": np.asarray(model.pattern).tolist(),
               "gravity": float(model.gravity),
               "status_codes": "; ".join(f"{k}: {v}" for k, v in ROTARY_STATUS.items())},
    )


# ---- design optimisation ------------------------------------------------------------------


def optimise_design(model: RotaryDCDEA, start=(4e-3, 12e-3),
                    bounds=((2e-3, 7e-3), (4e-3, 18e-3)), *, maxiter: int = 100,
                    gtol: float = 1e-9) -> dict:
    """Maximise the steady angle ``|theta|`` over ``(r_i, d)`` within ``bounds`` (m) by
    L-BFGS-B with exact gradients (IFT through the equilibrium, :func:`steady_angle`).

    Returns ``dict(r_i, d, theta_deg, nit, success, path)`` (``path``: the iterates, m).
    """
    from scipy.optimize import minimize

    lo = np.array([b[0] for b in bounds]) * 1e3
    hi = np.array([b[1] for b in bounds]) * 1e3
    fun = _objective_fn()
    path = []

    def f(x_mm):
        x = np.clip(x_mm, lo, hi)
        val, grad = fun(model, jnp.asarray(x * 1e-3))
        path.append(x * 1e-3)
        return float(val), np.asarray(grad, dtype=np.float64) * 1e-3

    res = minimize(f, np.asarray(start, dtype=np.float64) * 1e3, jac=True, method="L-BFGS-B",
                   bounds=list(zip(lo, hi)), options={"maxiter": maxiter, "gtol": gtol,
                                                      "ftol": 1e-15})
    x = np.clip(res.x, lo, hi) * 1e-3
    theta = -float(fun(model, jnp.asarray(x))[0])
    return {"r_i": float(x[0]), "d": float(x[1]), "theta_deg": theta, "nit": int(res.nit),
            "success": bool(res.success), "path": np.array(path)}


_OBJECTIVE = None


def _objective_fn():
    """Jitted ``(model, [r_i, d]) -> (-|theta| in deg, gradient)`` (built once)."""
    global _OBJECTIVE
    if _OBJECTIVE is None:
        def neg_angle(x, model):
            return -jnp.abs(jnp.degrees(steady_angle(model.with_geometry(x[0], x[1]))))

        vg = jax.value_and_grad(neg_angle)
        _OBJECTIVE = eqx.filter_jit(lambda model, x: vg(x, model))
    return _OBJECTIVE


# ---- config ------------------------------------------------------------------------------

GEOMETRY_FIELDS = {
    "inner_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "outer_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "spacer_half_length": Field(0.0, math.inf, lo_open=True, unit="m"),
    "spacer_frame_half_thickness": Field(0.0, math.inf, unit="m"),
    "frame_half_thickness": Field(0.0, math.inf, unit="m"),
    "thickness": Field(0.0, math.inf, lo_open=True, unit="m"),
}
MATERIAL_SCALARS = {
    "relative_permittivity": Field(1.0, math.inf, unit="(-)"),
    "eta_v0": Field(0.0, math.inf, unit="Pa s"),
}
MATERIAL_LISTS = {
    "alpha": Field(-100.0, 100.0, unit="(-)"),
    "beta": Field(unit="Pa"),
    "gamma": Field(unit="Pa"),
}
SPACER_FIELDS = {
    "mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
    "inertia": Field(0.0, math.inf, lo_open=True, unit="kg m^2"),
    "gravity": Field(0.0, 100.0, unit="m/s^2"),
}
DRIVE_SCALARS = {
    "field_max": Field(0.0, math.inf, unit="V/m"),
    "filter_time": Field(0.0, math.inf, lo_open=True, unit="s"),
}
PATTERN_FIELD = Field(0.0, math.inf, unit="x eq-30 voltage")


def _list(table: dict, section: str, key: str, field: Field, n: int | None = None) -> Array:
    name = f"{section}.{key}"
    if key not in table:
        raise ConfigError(f"missing key in [{section}]: {key} (a list, each in {field.describe()})")
    val = table[key]
    if not isinstance(val, list) or not val:
        raise ConfigError(f"{name} must be a non-empty list of numbers in {field.describe()}")
    if n is not None and len(val) != n:
        raise ConfigError(f"{name} must have {n} entries, got {len(val)}")
    return _f64([field.check(f"{name}[{i}]", x) for i, x in enumerate(val)])


def model_from_config(cfg: dict[str, Any]) -> RotaryDCDEA:
    """Validated :class:`RotaryDCDEA` from a parsed ``configs/rotary_dcdea.toml``."""
    allowed = {"model", "field", "geometry", "material", "spacer", "drive"}
    unknown = sorted(set(cfg) - allowed)
    if unknown:
        raise ConfigError(f"unknown top-level key(s): {', '.join(unknown)}; "
                          f"allowed: {', '.join(sorted(allowed))}")
    for key in ("geometry", "material", "spacer", "drive"):
        if key not in cfg:
            raise ConfigError(f"missing table: [{key}]")
    field = cfg.get("field", "frozen")
    if field not in FIELD_MODES:
        raise ConfigError(f"field = {field!r} is not one of {', '.join(FIELD_MODES)}")

    geo = _section(cfg["geometry"], "geometry", GEOMETRY_FIELDS)
    mat_tab = dict(cfg["material"])
    lists = {k: _list(mat_tab, "material", k, fld) for k, fld in MATERIAL_LISTS.items()}
    if not len({int(v.shape[0]) for v in lists.values()}) == 1:
        raise ConfigError("material.alpha, material.beta and material.gamma must have the same "
                          "number of terms N")
    if not bool(jnp.all(lists["alpha"] != 0)):
        raise ConfigError("material.alpha entries must be non-zero, allowed range "
                          "[-100, 0) or (0, 100]")
    mat = _section({k: v for k, v in mat_tab.items() if k not in MATERIAL_LISTS}, "material",
                   MATERIAL_SCALARS)
    spacer = _section(cfg["spacer"], "spacer", SPACER_FIELDS)
    drv_tab = dict(cfg["drive"])
    pattern = _list(drv_tab, "drive", "pattern", PATTERN_FIELD, n=4)
    drv = _section({k: v for k, v in drv_tab.items() if k != "pattern"}, "drive", DRIVE_SCALARS)

    model = RotaryDCDEA(
        r_i=geo["inner_radius"], r_o=geo["outer_radius"], d=geo["spacer_half_length"],
        f=geo["spacer_frame_half_thickness"], h=geo["frame_half_thickness"], z0=geo["thickness"],
        mass=spacer["mass"], inertia=spacer["inertia"], gravity=spacer["gravity"],
        material=OgdenTypeDE(alpha=tuple(float(a) for a in lists["alpha"]), beta=lists["beta"],
                             gamma=lists["gamma"], eps_r=mat["relative_permittivity"],
                             eta_v0=mat["eta_v0"]),
        field_max=drv["field_max"], pattern=pattern, filter_time=drv["filter_time"], field=field,
    )
    check_geometry(model)
    rest = equilibrium(model, jnp.zeros(4))
    if int(rest.status) != OK:
        raise ConfigError("no stable unactuated equilibrium (" + ROTARY_STATUS[int(rest.status)]
                          + "): check [geometry] and [material] values")
    return model

