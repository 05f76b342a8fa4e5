"""RC model of a deformable DEA capacitor fed through two resistive electrodes.

Paper 000 eqs 3-5 (eq 4 as printed reads ``1/c``; it is ``1/C``):
``dQ/dt = (Phi_in - Q/C) / (2 R_s)``, ``Phi_DEA = Q / C``,
``C = eps_r eps0 pi (b^2 - a^2) / (H_m cos(alpha))``.

The charge equation is linear in ``Q`` for a frozen geometry, with rate
``kappa = 1/(2 R_s C)`` (about 1/49 us for the reference cone): this is the stiff part of the
system, which :mod:`jaxdea.solver` integrates exactly.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def capacitance(eps: ArrayLike, a: ArrayLike, b: ArrayLike, thickness: ArrayLike,
                cos_alpha: ArrayLike) -> Array:
    """Capacitance of the annular cone (eq 5); ``eps = eps_r eps0``."""
    return eps * jnp.pi * (b * b - a * a) / (thickness * cos_alpha)


def charge_rate(phi_in: ArrayLike, charge: ArrayLike, cap: ArrayLike,
                resistance: ArrayLike) -> Array:
    """Current into the capacitor, ``(Phi_in - Q/C) / (2 R_s)`` (eq 3)."""
    return (phi_in - charge / cap) / (2.0 * resistance)
