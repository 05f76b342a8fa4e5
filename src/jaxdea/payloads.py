"""Dissipative payloads driven by the actuator.

Paper 000 (Fig 3, eq 19): a mass ``M`` moving against a linear viscous dashpot ``c``,
``f(v) = c v``. Gravity is neglected (horizontal motion).
"""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, ArrayLike


class LinearViscous(eqx.Module):
    """Payload mass ``mass`` (kg) with viscous damping ``damping`` (N s/m)."""

    mass: ArrayLike
    damping: ArrayLike

    def resisting_force(self, v: ArrayLike) -> Array:
        """Force the payload opposes to motion, ``f(v) = c v`` (eq 19)."""
        return self.damping * v
