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


def double_cone_lengths(q: ArrayLike, r_i: ArrayLike, r_o: ArrayLike, d: ArrayLike,
                        f: ArrayLike, h: ArrayLike) -> Array:
    """Lengths ``[l_A, l_B, l_C, l_D]`` of the four lumped DE elements of the rotational
    double cone (paper 003 eqs 16-24), for spacer coordinates ``q = [G_x, G_y, theta]``.

    Outer (fixed) points ``K1 = (-+r_o, +-h)`` (eqs 16, 18, 20, 22); inner points on the
    spacer ``K2 = G + R(theta) s_K`` with ``s_A = (-r_i, d+f)``, ``s_B = (r_i, d+f)``,
    ``s_C = (-r_i, -(d+f))``, ``s_D = (r_i, -(d+f))`` (eqs 17, 19, 21, 23);
    ``l_K = ||K2 - K1||`` (eq 24). All lengths in m, theta in rad.
    """
    q = jnp.asarray(q)
    gx, gy, th = q[0], q[1], q[2]
    c, s = jnp.cos(th), jnp.sin(th)
    a = d + f
    sx = jnp.stack([-r_i, r_i, -r_i, r_i])      # spacer-frame x of A, B, C, D
    sy = jnp.stack([a, a, -a, -a])              # spacer-frame y of A, B, C, D
    k1x = jnp.stack([-r_o, r_o, -r_o, r_o])
    k1y = jnp.stack([h, h, -h, -h])
    k2x = gx + c * sx - s * sy
    k2y = gy + s * sx + c * sy
    return jnp.sqrt((k2x - k1x) ** 2 + (k2y - k1y) ** 2)
