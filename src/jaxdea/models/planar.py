"""Clamped pure-shear planar DEA of paper 004 (Gu et al., IEEE T-RO 2017), eqs 4-15.

A VHB 4910 membrane ``L1 x L2 x H`` is prestretched by ``lam2p`` across and clamped, and a
dead load ``P1`` stretches it to ``lam1p`` along direction 1. Under the voltage ``phi`` it
lengthens; ``lam2 = lam2p`` stays fixed (pure shear). Material: Gent equilibrium spring in
parallel with ``n`` Gent spring-dashpot units (:class:`jaxdea.materials.GentSpringDashpot`,
deviatoric flow of eqs 7-8).

State ``(lam1, xi1, xi2)``; ``xi1, xi2`` have shape ``(n,)``.

- eq 5: ``sigma_1 + eps E^2 = s_eq(lam1, lam2) + sum_i s_i(lam1/xi_i1, lam2/xi_i2)``
- eq 11: ``P1 = L2 H s_eq(lam1p, lam2p) / lam1p`` (the dashpots are relaxed at t = 0)
- eq 12: ``P1 = (L2 H / lam1) (sigma_1 + eps E^2 - eps E^2)``, ``E = phi lam1 lam2 / H``
  (since ``sigma_1 = P1/(l2 h)``, ``l2 h = L2 H / lam1``)
- eqs 13-14: ``dP1/dt = 0`` -> ``dlam1/dt = -(dP1/dphi dphi/dt + sum dP1/dxi dxi/dt) /
  dP1/dlam1`` (the partials by forward-mode AD, ``dphi/dt`` of the drive likewise)
- eqs 7-8: dashpot rates; eq 9: ``eta_i = mu_i tau_i``.

The paper's ``mu_1, J_1`` (equilibrium spring) are ``material.mu0, J0`` here and its units
``i = 2..n`` are ``material.mu[i-2]`` etc.; its ``T_{i-1}`` is ``material.tau[i-2]``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ..materials import EPS0, GentSpringDashpot, gent_denominator

__all__ = ["PlanarDEA", "GU2017_MODELS", "gu2017"]


class PlanarDEA(eqx.Module):
    """Paper 004's clamped pure-shear DEA (SI fields). ``eps`` is the permittivity (F/m)."""

    L1: ArrayLike  #: reference length along the load, m
    L2: ArrayLike  #: reference width, m
    H: ArrayLike  #: reference thickness, m
    lam1p: ArrayLike  #: prestretch along the load (by the dead load P1)
    lam2p: ArrayLike  #: prestretch across (clamped)
    eps: ArrayLike  #: permittivity, F/m
    material: GentSpringDashpot

    def load(self) -> Array:
        """Dead load ``P1`` (N), eq 11: the relaxed membrane at ``(lam1p, lam2p)``, phi = 0."""
        s_eq, _ = self.material.equilibrium_stresses(self.lam1p, self.lam2p)
        return self.L2 * self.H * s_eq / self.lam1p

    def force(self, phi: ArrayLike, lam1: ArrayLike, xi1: Array, xi2: Array) -> Array:
        """``P1 = f(phi, lam1, lam2, xi)`` of eq 12 (N)."""
        s1, _ = self.material.stresses(lam1, self.lam2p, xi1, xi2)
        field = phi * lam1 * self.lam2p / self.H
        return self.L2 * self.H / lam1 * (s1 - self.eps * field * field)

    def initial_state(self) -> tuple[Array, Array, Array]:
        """Prestretched, relaxed state (paper 004, text above eq 10)."""
        n = jnp.shape(self.material.mu)[-1]
        one = jnp.ones(n)
        lam1p = jnp.asarray(self.lam1p, float)
        return lam1p, lam1p * one, jnp.asarray(self.lam2p, float) * one

    def vector_field(self, t, y, signal):
        """Eq 15: ``(dlam1/dt, dxi1/dt, dxi2/dt)``."""
        lam1, xi1, xi2 = y
        phi, dphi = jax.jvp(signal, (t,), (jnp.ones_like(t),))
        dxi1, dxi2 = self.material.dashpot_rates(lam1, self.lam2p, xi1, xi2)
        _, num = jax.jvp(lambda p, a, b: self.force(p, lam1, a, b), (phi, xi1, xi2),
                         (dphi, dxi1, dxi2))
        _, den = jax.jvp(lambda lam: self.force(phi, lam, xi1, xi2), (lam1,),
                         (jnp.ones_like(lam1),))
        return -num / den, dxi1, dxi2

    def observables(self, t, y, signal) -> dict:
        lam1, xi1, xi2 = y
        return {
            "voltage": signal(t),
            "displacement": (lam1 - self.lam1p) * self.L1,
            "lam1": lam1,
            "lam2": jnp.asarray(self.lam2p, float) * jnp.ones_like(lam1),
        }

    def check(self) -> None:
        """Raise ``ValueError`` naming the field if a parameter is out of range at the
        prestretched state (non-positive relaxation time, Gent lock-up, ...)."""
        m = self.material
        for name, val in (("L1", self.L1), ("L2", self.L2), ("H", self.H),
                          ("eps", self.eps), ("material.mu0", m.mu0), ("material.J0", m.J0)):
            if not float(val) > 0:
                raise ValueError(f"{name} = {float(val)!r} must be > 0 (allowed range (0, inf))")
        for name, arr in (("mu", m.mu), ("J", m.J), ("tau", m.tau)):
            for i, v in enumerate(jnp.atleast_1d(arr)):
                if not float(v) > 0 or not math.isfinite(float(v)):
                    raise ValueError(f"material.{name}[{i}] = {float(v)!r} must be > 0 "
                                     f"(allowed range (0, inf)); a relaxation time must be "
                                     f"positive")
        inv = float(m.J0 * (1.0 - gent_denominator(self.lam1p, self.lam2p, m.J0)))
        if not float(m.J0) > inv:
            raise ValueError(f"material.J0 = {float(m.J0):g} is below the stretch invariant "
                             f"I1 - 3 = {inv:.4g} at the prestretch (Gent lock-up); allowed "
                             f"range ({inv:.4g}, inf)")


#: Paper 004's three parameter sets (section V): ``(mu0, [mu_i], [tau_i])`` in Pa, Pa, s;
#: every J = 155.
GU2017_MODELS = {
    "model1": (78e3, [65e3], [0.85]),
    "model2": (62e3, [40e3, 30e3], [0.5, 5.0]),
    "final": (15e3, [150e3, 20e3, 25e3, 12e3], [0.18, 6.0, 145.0, 550.0]),
}


def gu2017(which: str = "final", eps_r: float = 4.7) -> PlanarDEA:
    """Paper 004's DEA with parameter set ``which`` (``model1``, ``model2``, ``final``).

    Geometry (section II.A): L1 = 20 mm, L2 = 70 mm, H = 1 mm, lam1p = 1.5, lam2p = 2.
    ``eps_r`` = 4.7 is chosen (VHB; the paper does not print it).
    """
    mu0, mu, tau = GU2017_MODELS[which]
    n = len(mu)
    mat = GentSpringDashpot(mu0=jnp.asarray(mu0, float), J0=jnp.asarray(155.0),
                            mu=jnp.asarray(mu, float), J=jnp.full(n, 155.0),
                            tau=jnp.asarray(tau, float), flow="deviatoric")
    return PlanarDEA(L1=jnp.asarray(0.02), L2=jnp.asarray(0.07), H=jnp.asarray(1e-3),
                     lam1p=jnp.asarray(1.5), lam2p=jnp.asarray(2.0),
                     eps=jnp.asarray(eps_r * EPS0), material=mat)
