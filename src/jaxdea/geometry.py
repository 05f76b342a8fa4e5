"""Cone kinematics: radial stretch and cone angle from the out-of-plane deflection.

Paper 000 eqs 1-2, with the deflection ``d`` signed (+x towards the payload) so that one
function serves membrane B (at +d0) and the mirrored membrane A of double cones (at -d0).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def cone_kinematics(d: ArrayLike, a: ArrayLike, b: ArrayLike) -> tuple[Array, Array, Array]:
    """Return ``(lam1', sin(alpha), cos(alpha))`` of a truncated cone of deflection ``d``.

    ``lam1' = sqrt(d^2 + (b-a)^2) / (b-a)`` (eq 1), ``sin(alpha) = d / sqrt(d^2 + (b-a)^2)``
    (eq 2, signed), ``cos(alpha) = (b-a) / sqrt(...) = 1/lam1'``.
    """
    d = jnp.asarray(d)
    w = b - a
    slant = jnp.sqrt(d * d + w * w)
    return slant / w, d / slant, w / slant
