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
        return xi * (s1 - 0.5 * s2) / (3.0 * self.mu_B * self.tau)

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
