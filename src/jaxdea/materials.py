"""Constitutive laws: Gent springs, Maxwell (spring-dashpot) branches, electrostatic stress.

All functions are pure and elementwise, so they broadcast over membranes, lanes and grids.
Stresses are true (Cauchy) stresses in Pa along the loading direction 1, for an
incompressible membrane with in-plane stretches ``l1`` (loading) and ``l2`` (transverse).

Seed equations: paper 000 eqs 11.a-c, 13.a-b, 14 (partly garbled in the extraction);
rebuilt from paper 004 (Gu et al. 2017) eqs 4-9, which write the Gent + spring-dashpot law
cleanly. See docs/models.md.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

#: Vacuum permittivity, F/m.
EPS0 = 8.854187817e-12


def gent_stress(l1: ArrayLike, l2: ArrayLike, mu: ArrayLike, J: ArrayLike) -> Array:
    """Gent spring stress along direction 1 (paper 000 eq 11.a / 13.a; paper 004 eq 4).

    ``s = mu (l1^2 - l1^-2 l2^-2) / (1 - (l1^2 + l2^2 + l1^-2 l2^-2 - 3) / J)``.
    Valid while the denominator is positive (below Gent lock-up).
    """
    l1 = jnp.asarray(l1)
    l2 = jnp.asarray(l2)
    inv = 1.0 / (l1 * l1 * l2 * l2)
    return mu * (l1 * l1 - inv) / gent_denominator(l1, l2, J)


def gent_denominator(l1: ArrayLike, l2: ArrayLike, J: ArrayLike) -> Array:
    """``1 - (I1 - 3)/J``: the Gent stiffening factor; <= 0 means the chains have locked up."""
    l1 = jnp.asarray(l1)
    l2 = jnp.asarray(l2)
    return 1.0 - (l1 * l1 + l2 * l2 + 1.0 / (l1 * l1 * l2 * l2) - 3.0) / J


class GentMaxwell(eqx.Module):
    """Gent equilibrium spring in parallel with one Gent spring-dashpot (Maxwell) branch.

    Paper 000 eqs 11-14 (the same law for the dielectric and for the elastomeric electrodes,
    with their own parameters). Assumption (iv) of paper 000: the branch's transverse elastic
    stretch stays 1 and only the radial dashpot stretch ``xi`` evolves.

    Fields (SI): ``mu_A`` equilibrium shear modulus (Pa), ``J_A`` its Gent limit,
    ``mu_B`` branch shear modulus (Pa), ``J_B`` its Gent limit, ``tau`` branch relaxation time
    (s), so the dashpot viscosity is ``eta = mu_B * tau`` (Pa s).
    """

    mu_A: ArrayLike
    J_A: ArrayLike
    mu_B: ArrayLike
    J_B: ArrayLike
    tau: ArrayLike

    def equilibrium_stress(self, l1: ArrayLike, l2: ArrayLike) -> Array:
        """Hyperelastic stress of the equilibrium spring (eq 11.a / 13.a)."""
        return gent_stress(l1, l2, self.mu_A, self.J_A)

    def branch_stresses(self, l1: ArrayLike, xi: ArrayLike) -> tuple[Array, Array]:
        """Branch stresses ``(s_1, s_2)`` at elastic stretches ``(l1/xi, 1)`` (eq 11.b-c)."""
        l1e = jnp.asarray(l1) / xi
        one = jnp.ones_like(l1e)
        s1 = gent_stress(l1e, one, self.mu_B, self.J_B)
        s2 = gent_stress(one, l1e, self.mu_B, self.J_B)
        return s1, s2

    def viscous_stress(self, l1: ArrayLike, xi: ArrayLike) -> Array:
        """Stress carried by the Maxwell branch along direction 1 (eq 11.b)."""
        return self.branch_stresses(l1, xi)[0]

    def dashpot_driving_stress(self, l1: ArrayLike, xi: ArrayLike) -> Array:
        """Deviatoric stress on the dashpot, ``s_1 - s_2 / 2`` (eq 14 = paper 004 eq 7)."""
        s1, s2 = self.branch_stresses(l1, xi)
        return s1 - 0.5 * s2

    def _rate(self, xi: ArrayLike, s1: Array, s2: Array) -> Array:
        """Eq 14 from the branch stresses: ``xi (s_1 - s_2/2) / (3 eta)``, ``eta = mu_B tau``."""
        return deviatoric_flow(xi, s1, s2, self.mu_B * self.tau)

    def dashpot_rate(self, l1: ArrayLike, xi: ArrayLike) -> Array:
        """``d xi / dt`` of the dashpot (eq 14)."""
        return self._rate(xi, *self.branch_stresses(l1, xi))

    def stress_and_rate(self, l1: ArrayLike, l2: ArrayLike, xi: ArrayLike) -> tuple[Array, Array]:
        """Total mechanical stress (equilibrium spring + Maxwell branch; eq 10 / 12 less the
        electrostatic term) and ``dashpot_rate``, sharing one branch evaluation (the hot path
        of every simulation)."""
        s1, s2 = self.branch_stresses(l1, xi)
        return self.equilibrium_stress(l1, l2) + s1, self._rate(xi, s1, s2)

    def stress(self, l1: ArrayLike, l2: ArrayLike, xi: ArrayLike) -> Array:
        """Total mechanical stress (first output of :meth:`stress_and_rate`)."""
        return self.stress_and_rate(l1, l2, xi)[0]

def electrostatic_stress(eps: ArrayLike, field: ArrayLike) -> Array:
    """Maxwell stress of the electric field, ``-eps E^2`` (paper 000 eq 10, third term)."""
    field = jnp.asarray(field)
    return -eps * field * field


def ogden_type_stress(lam: ArrayLike, lam_dot: ArrayLike, field: ArrayLike, alpha: ArrayLike,
                      beta: ArrayLike, gamma: ArrayLike, eps: ArrayLike,
                      eta: ArrayLike) -> Array:
    """True radial stress of the lumped cone DE of paper 003 (eq 10), in Pa.

    ``sigma = sum_i (beta_i lam^alpha_i - gamma_i lam^-alpha_i) - eps E^2 + eta lam_dot``:
    a modified N-th order Ogden law (pure shear) with the electrostatic stress and a linear
    viscous term. ``alpha``, ``beta`` (Pa), ``gamma`` (Pa) have shape ``(N,)`` (the terms are
    summed over the last axis); ``lam``, ``lam_dot`` (1/s) and ``field`` (V/m) broadcast;
    ``eps = eps0 eps_r`` (F/m), ``eta`` the damping coefficient eta_v0 (Pa s).
    ``alpha`` may be a tuple of Python numbers (static exponents): integer-valued ones are
    then evaluated as products (``lax.integer_pow``), several times faster than ``pow``.
    """
    if isinstance(alpha, (tuple, list)):
        lam = jnp.asarray(lam)
        elastic = 0.0
        for i, a in enumerate(alpha):
            p = lam ** int(a) if float(a).is_integer() else lam ** float(a)
            elastic = elastic + beta[i] * p - gamma[i] / p
    else:
        lam = jnp.asarray(lam)[..., None]
        elastic = jnp.sum(beta * lam ** alpha - gamma * lam ** (-jnp.asarray(alpha)), axis=-1)
    return elastic + electrostatic_stress(eps, field) + eta * jnp.asarray(lam_dot)


# --- Gent + n spring-dashpot units, generalized Kelvin chain (papers 001, 002, 004) ---------


def deviatoric_flow(xi: ArrayLike, s_along: ArrayLike, s_across: ArrayLike,
                    eta: ArrayLike) -> Array:
    """Newtonian dashpot driven by the deviatoric stress (paper 004 eqs 7-8; paper 000 eq 14).

    ``(1/xi) dxi/dt = (s_along - s_across/2) / (3 eta)``, with ``s_k = sigma_k - sigma_3`` the
    branch-spring stresses (direction 3 = thickness) and ``eta = mu tau`` (Pa s).
    """
    return xi * (s_along - 0.5 * s_across) / (3.0 * eta)


class GentSpringDashpot(eqx.Module):
    """Gent equilibrium spring in parallel with ``n`` Gent spring-dashpot units.

    Paper 004 Fig 5 and eqs 4-9 (also paper 002 Fig 3, eqs 19-23). Each unit ``i`` has a
    Gent spring ``(mu_i, J_i)`` in series with a Newtonian dashpot of viscosity
    ``eta_i = mu_i tau_i`` (eq 9 / 002 eq 23). The membrane has two tracked principal
    stretches ``(l1, l2)``; the third is ``1/(l1 l2)`` (incompressible). Unit ``i`` carries the
    dashpot stretches ``(xi1_i, xi2_i)`` and its spring the elastic stretches
    ``(l1/xi1_i, l2/xi2_i)`` (multiplicative split, 004 text above eq 4).

    ``flow`` (static) selects the dashpot law:

    - ``"deviatoric"``: paper 004 eqs 7-8, ``(1/xi_k) dxi_k/dt = (s_k - s_j/2)/(3 eta)``;
    - ``"conjugate"``: paper 002 eqs 21-22, ``-xi_k dW_i/dxi_k = eta dxi_k/dt``, i.e.
      ``dxi_k/dt = s_k / eta`` with ``s_k = sigma_k - sigma_3`` the unit's spring stress.

    Fields (SI): ``mu0`` (Pa), ``J0``; ``mu``, ``J``, ``tau`` (s) of shape ``(n,)``.
    """

    mu0: ArrayLike
    J0: ArrayLike
    mu: Array
    J: Array
    tau: Array
    flow: str = eqx.field(static=True, default="deviatoric")

    @property
    def eta(self) -> Array:
        """Dashpot viscosities ``eta_i = mu_i tau_i`` (Pa s; 004 eq 9, 002 eq 23)."""
        return self.mu * self.tau

    def equilibrium_stresses(self, l1: ArrayLike, l2: ArrayLike) -> tuple[Array, Array]:
        """``(sigma_1 - sigma_3, sigma_2 - sigma_3)`` of the equilibrium spring (004 eqs 5-6)."""
        return (gent_stress(l1, l2, self.mu0, self.J0), gent_stress(l2, l1, self.mu0, self.J0))

    def branch_stresses(self, l1: ArrayLike, l2: ArrayLike, xi1: Array,
                        xi2: Array) -> tuple[Array, Array]:
        """Per-unit spring stresses ``(s_1, s_2)``, shape ``(n,)`` (the sums of 004 eqs 5-6)."""
        e1 = jnp.asarray(l1) / xi1
        e2 = jnp.asarray(l2) / xi2
        return gent_stress(e1, e2, self.mu, self.J), gent_stress(e2, e1, self.mu, self.J)

    def stresses(self, l1: ArrayLike, l2: ArrayLike, xi1: Array,
                 xi2: Array) -> tuple[Array, Array]:
        """Total mechanical ``(sigma_1 + eps E^2, sigma_2 + eps E^2)``: 004 eqs 5-6."""
        a1, a2 = self.equilibrium_stresses(l1, l2)
        b1, b2 = self.branch_stresses(l1, l2, xi1, xi2)
        return a1 + jnp.sum(b1, axis=-1), a2 + jnp.sum(b2, axis=-1)

    def dashpot_rates(self, l1: ArrayLike, l2: ArrayLike, xi1: Array,
                      xi2: Array) -> tuple[Array, Array]:
        """``(dxi1/dt, dxi2/dt)`` per unit: 004 eqs 7-8 or 002 eq 22 (see ``flow``)."""
        s1, s2 = self.branch_stresses(l1, l2, xi1, xi2)
        eta = self.eta
        if self.flow == "deviatoric":
            return deviatoric_flow(xi1, s1, s2, eta), deviatoric_flow(xi2, s2, s1, eta)
        if self.flow == "conjugate":
            return s1 / eta, s2 / eta
        raise ValueError(f"flow must be 'deviatoric' or 'conjugate', got {self.flow!r}")

    def stress_invariant(self, l1: ArrayLike, l2: ArrayLike, xi1: Array,
                         xi2: Array) -> tuple[Array, Array]:
        """``I1 - 3`` of the equilibrium spring and of each unit spring (for Gent checks)."""
        i0 = self.J0 * (1.0 - gent_denominator(l1, l2, self.J0))
        e1, e2 = jnp.asarray(l1) / xi1, jnp.asarray(l2) / xi2
        return i0, self.J * (1.0 - gent_denominator(e1, e2, self.J))


class GentKelvinChain(eqx.Module):
    """Generalized Kelvin chain of Gent springs (paper 001 Fig 11, eqs 28-32).

    An elastic Gent spring ``(mu1, J1)`` in series with ``n`` Kelvin-Voigt elements (Gent
    spring ``(mu_k, J_k)`` parallel to a dashpot ``eta_k``). Series elements compose
    multiplicatively: ``lam = xi_1 prod_k xi_k`` (the thesis writes a sum, which its own
    initial state x0 contradicts; see docs/models.md). Every element deforms in the same
    constrained mode, the second in-plane stretch fixed at ``l2`` (``l2 = 1`` for the cone's
    circumferential direction), and all carry the same stress (thesis eq 31):

    ``sigma = s(xi_1; mu1, J1) = s(xi_k; mu_k, J_k) + eta_k dxi_k/dt``,  with
    ``s(x) = gent_stress(x, l2)`` (eq 30 without the electrostatic term).

    Eq 32 as printed has the opposite (unstable) sign; the rate here is
    ``dxi_k/dt = (sigma - s(xi_k)) / eta_k``. Fields (SI): ``mu1`` (Pa), ``J1``; ``mu``,
    ``J``, ``eta`` (Pa s) of shape ``(n,)``.
    """

    mu1: ArrayLike
    J1: ArrayLike
    mu: Array
    J: Array
    eta: Array

    def elastic_stretch(self, lam: ArrayLike, xi: Array) -> Array:
        """Stretch of the dashpot-free spring, ``xi_1 = lam / prod_k xi_k``."""
        return jnp.asarray(lam) / jnp.prod(xi, axis=-1)

    def stress(self, lam: ArrayLike, xi: Array, l2: ArrayLike = 1.0) -> Array:
        """Chain stress ``sigma = s(xi_1; mu1, J1)`` (eq 30 less ``eps E^2``)."""
        return gent_stress(self.elastic_stretch(lam, xi), l2, self.mu1, self.J1)

    def rates(self, lam: ArrayLike, xi: Array, l2: ArrayLike = 1.0) -> Array:
        """``dxi_k/dt = (sigma - s(xi_k; mu_k, J_k)) / eta_k`` (eq 31, sign-corrected eq 32)."""
        sigma = self.stress(lam, xi, l2)
        return (jnp.asarray(sigma)[..., None] - gent_stress(xi, l2, self.mu, self.J)) / self.eta
