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
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._checks import ConfigError
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
                      ) -> RotaryDCDEA:
        """Copy with a new inner radius and/or half spacer length (m)."""
        out = self
        if r_i is not None:
            out = eqx.tree_at(lambda m: m.r_i, out, jnp.asarray(r_i, dtype=jnp.float64))
        if d is not None:
            out = eqx.tree_at(lambda m: m.d, out, jnp.asarray(d, dtype=jnp.float64))
        return out

    def with_pattern(self, pattern: ArrayLike) -> RotaryDCDEA:
        """Copy with another activation pattern (4 multipliers of the eq-30 voltage, A-D)."""
        return eqx.tree_at(lambda m: m.pattern, self, jnp.asarray(pattern, dtype=jnp.float64))

    def with_field(self, field: str) -> RotaryDCDEA:
        """Copy with the other eq-9 reading ("frozen" or "literal")."""
        if field not in FIELD_MODES:
            raise ConfigError(f"field = {field!r} is not one of {', '.join(FIELD_MODES)}")
        return _replace_static(self, field)


def _replace_static(model: RotaryDCDEA, field: str) -> RotaryDCDEA:
    kw = {k: getattr(model, k) for k in model.__dataclass_fields__}
    kw["field"] = field
    return RotaryDCDEA(**kw)


def f64(x) -> Array:
    return jnp.asarray(x, dtype=jnp.float64)


def paper_model(r_i: float = 2e-3, d: float = 7e-3, *, gravity: float = 0.0,
                field: str = "frozen", pattern=(0.0, 1.0, 1.0, 0.0), mass: float = 5e-3,
                inertia: float = 1e-6, z0: float = 50e-6, filter_time: float = 0.05,
                check: bool = True) -> RotaryDCDEA:
    """Table 1 of paper 003 with the given ``r_i``, ``d`` (m); the rest as in
    ``configs/rotary_dcdea.toml``. ``check`` raises :class:`ConfigError` on invalid geometry."""
    model = RotaryDCDEA(
        r_i=f64(r_i), r_o=f64(22.5e-3), d=f64(d), f=f64(0.0), h=f64(2e-3), z0=f64(z0),
        mass=f64(mass), inertia=f64(inertia), gravity=f64(gravity),
        material=OgdenTypeDE(alpha=(2.0, 4.0), beta=f64([1.707e6, -0.023e6]),
                             gamma=f64([1.298e6, -0.955e6]), eps_r=f64(2.8),
                             eta_v0=f64(0.2e6)),
        field_max=f64(80e6), pattern=f64(pattern), filter_time=f64(filter_time),
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


def scales(model: RotaryDCDEA) -> Array:
    """Variable scales ``[L, L, 1]`` (L = r_o - r_i) for convergence tests and stiffness."""
    span = model.r_o - model.r_i
    return jnp.stack([span, span, jnp.ones_like(span)])


def _residual_and_jacobian(model: RotaryDCDEA, q: Array, v: Array) -> tuple[Array, Array]:
    """Static residual and its Jacobian ``dR/dq`` (forward-mode autodiff)."""
    return model.static_residual(q, v), jax.jacfwd(model.static_residual)(q, v)


def _scaled_sym(model: RotaryDCDEA, dres: Array) -> Array:
    """Stiffness ``-dR/dq`` scaled to ``[G/L, G/L, theta]`` and symmetrised."""
    scale = scales(model)
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
    scale = scales(safe)

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
