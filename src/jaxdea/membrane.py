"""A cone membrane: geometry + prestretched dielectric + two elastomeric electrode layers.

This is the one place where paper 000's membrane law lives; every cone configuration
(single cone, double cones) reuses it. All methods are elementwise in the deflection, so an
array of deflections evaluates several identical membranes at once.

Per membrane the internal state is ``(Q, xi_m, xi_el)``: charge and the dashpot stretches of
the dielectric's and the electrodes' Maxwell branches.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .electrical import capacitance, charge_rate
from .geometry import cone_kinematics
from .materials import EPS0, GentMaxwell, electrostatic_stress, gent_denominator

#: Default dielectric breakdown field of the membrane, V/m: 100 V/um, the order that WACKER's
#: data sheet for ELASTOSIL Film 2030 (the papers' film) gives and that breakdown tests of
#: the film report, prestretch raising it and carbon electrodes lowering it by up to 20 %
#: (docs/models.md, section 5). Paper 000 drives at 80 MV/m, below it. Only checked, never
#: used in the dynamics (config key ``drive.breakdown_field``).
BREAKDOWN_FIELD = 100e6


class MembraneResponse(NamedTuple):
    """What a membrane exerts and how its internal state moves, at one instant."""

    force: Array  #: axial force on the central disk, N (eq 15; restoring, odd in d)
    current: Array  #: dQ/dt, A (eq 3)
    dxi_m: Array  #: d xi_m / dt of the dielectric's dashpot, 1/s (eq 14.a)
    dxi_el: Array  #: d xi_el / dt of the electrodes' dashpot, 1/s (eq 14.b)
    voltage: Array  #: Phi_DEA = Q/C, V (eq 4)


class ConeMembrane(eqx.Module):
    """Paper 000's cone DEA membrane (eqs 1-15). SI units throughout.

    Fields: ``inner_radius`` a (disk), ``outer_radius`` b (frame), ``thickness`` H_m0 of the
    unstretched dielectric, ``prestretch`` lam_p (equi-biaxial, before the electrodes are
    printed), ``relative_permittivity`` eps_r, ``electrode_thickness`` H_el0,
    ``electrode_resistance`` R_s (surface resistance of one electrode), and the Gent-Maxwell
    laws of the ``dielectric`` and of the ``electrode`` layers.
    """

    inner_radius: ArrayLike
    outer_radius: ArrayLike
    thickness: ArrayLike
    prestretch: ArrayLike
    relative_permittivity: ArrayLike
    electrode_thickness: ArrayLike
    electrode_resistance: ArrayLike
    dielectric: GentMaxwell
    electrode: GentMaxwell

    @property
    def permittivity(self) -> Array:
        return self.relative_permittivity * EPS0

    def kinematics(self, d: ArrayLike):
        """Stretches and thicknesses at deflection ``d`` (eqs 1-2, 6-9).

        Returns ``(lam_m1, lam_m2, lam_el1, H_m, H_el, sin_alpha, cos_alpha)``; the electrode's
        circumferential stretch is 1 (printed on the prestretched film, assumption iv).
        """
        lam1, sin_a, cos_a = cone_kinematics(d, self.inner_radius, self.outer_radius)
        lam_m1 = lam1 * self.prestretch  # eq 6
        lam_m2 = self.prestretch * jnp.ones_like(lam1)  # assumption (iv)
        h_m = self.thickness / (lam_m1 * lam_m2)  # eq 8
        h_el = self.electrode_thickness / lam1  # eq 9 with lam_el2 = 1
        return lam_m1, lam_m2, lam1, h_m, h_el, sin_a, cos_a

    def capacitance(self, d: ArrayLike) -> Array:
        """Capacitance at deflection ``d`` (eq 5)."""
        *_, h_m, _, _, cos_a = self.kinematics(d)
        return capacitance(self.permittivity, self.inner_radius, self.outer_radius, h_m, cos_a)

    def charge_relaxation_rate(self, d: ArrayLike) -> Array:
        """``kappa = 1 / (2 R_s C)``: the (fast) rate of the RC charge equation, 1/s."""
        return 1.0 / (2.0 * self.electrode_resistance * self.capacitance(d))

    def current(self, d: ArrayLike, charge: ArrayLike, phi_in: ArrayLike) -> Array:
        """Charging current ``dQ/dt`` at deflection ``d`` (eq 3)."""
        return charge_rate(phi_in, charge, self.capacitance(d), self.electrode_resistance)

    def relaxed_dashpots(self, d: ArrayLike) -> tuple[Array, Array]:
        """Dashpot stretches that leave both Maxwell branches stress-free at ``d``."""
        lam_m1, _, lam_el1, *_ = self.kinematics(d)
        return lam_m1, lam_el1

    def _axial(self, d, sigma_m, sigma_el, h_m, h_el, sin_a):
        """Eq 15: ``F = -2 pi a sin(alpha) (H_m sigma_m + 2 H_el sigma_el)``."""
        return -2.0 * jnp.pi * self.inner_radius * sin_a * (h_m * sigma_m + 2.0 * h_el * sigma_el)

    def static_force(self, d: ArrayLike) -> Array:
        """Axial force of the relaxed, uncharged membrane (equilibrium springs only)."""
        lam_m1, lam_m2, lam_el1, h_m, h_el, sin_a, _ = self.kinematics(d)
        sigma_m = self.dielectric.equilibrium_stress(lam_m1, lam_m2)
        sigma_el = self.electrode.equilibrium_stress(lam_el1, 1.0)
        return self._axial(d, sigma_m, sigma_el, h_m, h_el, sin_a)

    def respond(self, d: ArrayLike, charge: ArrayLike, xi_m: ArrayLike, xi_el: ArrayLike,
                phi_in: ArrayLike) -> MembraneResponse:
        """Force and internal-state rates at deflection ``d`` under source voltage ``phi_in``."""
        lam_m1, lam_m2, lam_el1, h_m, h_el, sin_a, cos_a = self.kinematics(d)
        cap = capacitance(self.permittivity, self.inner_radius, self.outer_radius, h_m, cos_a)
        voltage = charge / cap
        mech_m, dxi_m = self.dielectric.stress_and_rate(lam_m1, lam_m2, xi_m)
        sigma_m = mech_m + electrostatic_stress(self.permittivity, voltage / h_m)  # eq 10
        sigma_el, dxi_el = self.electrode.stress_and_rate(lam_el1, 1.0, xi_el)  # eq 12
        return MembraneResponse(
            force=self._axial(d, sigma_m, sigma_el, h_m, h_el, sin_a),
            current=charge_rate(phi_in, charge, cap, self.electrode_resistance),
            dxi_m=dxi_m,
            dxi_el=dxi_el,
            voltage=voltage,
        )

    def gent_margin(self, d: ArrayLike, xi_m: ArrayLike, xi_el: ArrayLike) -> Array:
        """Smallest Gent denominator over all springs: <= 0 means lock-up (invalid state)."""
        lam_m1, lam_m2, lam_el1, *_ = self.kinematics(d)
        one = jnp.ones_like(lam_m1)
        return jnp.minimum(
            jnp.minimum(
                gent_denominator(lam_m1, lam_m2, self.dielectric.J_A),
                gent_denominator(lam_el1, one, self.electrode.J_A),
            ),
            jnp.minimum(
                gent_denominator(lam_m1 / xi_m, one, self.dielectric.J_B),
                gent_denominator(lam_el1 / xi_el, one, self.electrode.J_B),
            ),
        )
