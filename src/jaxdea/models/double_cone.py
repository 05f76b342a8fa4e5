"""Double cone DEAs of paper 000: rigid rod (DCDEA-RR) and linear spring (DCDEA-LS) coupling.

Membrane A sits at negative deflection (mirror image of B), membrane B carries the payload.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ..membrane import ConeMembrane
from ..payloads import PayloadLaw
from .cone import ConeActuator


class DCDEA_RR(ConeActuator):
    """Two cones joined by a rigid rod of length ``L_r`` (paper 000 eq 17, config II).

    One dof ``d_B``; ``d_A = d_B - L_r``. ``(2m + M) d_B'' = F_A(d_B - L_r) + F_B(d_B) - c d_B'``.
    No preload: the two membranes bias each other (rest at ``d_B = L_r / 2`` by symmetry).
    """

    membrane: ConeMembrane
    disk_mass: ArrayLike
    rod_length: ArrayLike

    n_dof: ClassVar[int] = 1
    membrane_names: ClassVar[tuple[str, ...]] = ("A", "B")
    payload_dof: ClassVar[int] = 0
    name: ClassVar[str] = "dcdea_rr"

    def deflections(self, q):
        return jnp.concatenate([q - self.rod_length, q])

    def accelerations(self, q, v, membrane_forces, payload: PayloadLaw):
        force = jnp.sum(membrane_forces) - payload.force(q, v)
        return force / (2.0 * self.disk_mass + payload.mass)

    def static_forces(self, q):
        return jnp.sum(self.membrane.static_force(self.deflections(q)), keepdims=True)

    def static_guess(self):
        return jnp.full((1,), 0.3) * self.rod_length


class DCDEA_LS(ConeActuator):
    """Two cones coupled by a linear compression spring (paper 000 eq 18, config III).

    Dofs ``(d_A, d_B)``: ``m d_A'' = F_A(d_A) - F_p``, ``(m + M) d_B'' = F_B(d_B) + F_p - c d_B'``,
    ``F_p = F0 - k ((d_B - d_A) - 2 d0)``, with the preload ``F0 = -F_B(d0)`` of the relaxed,
    uncharged membrane so that the disks rest at ``-d0`` and ``+d0`` (Table S.I is missing;
    reference/cone_power.md item 9).
    """

    membrane: ConeMembrane
    disk_mass: ArrayLike
    spring_stiffness: ArrayLike
    deflection: ArrayLike

    n_dof: ClassVar[int] = 2
    membrane_names: ClassVar[tuple[str, ...]] = ("A", "B")
    payload_dof: ClassVar[int] = 1
    name: ClassVar[str] = "dcdea_ls"

    @property
    def preload(self) -> Array:
        """Spring preload ``F0`` (N) that rests the relaxed, unactuated disks at ``-+d0``."""
        return -self.membrane.static_force(self.deflection)

    def spring_force(self, q: Array) -> Array:
        return self.preload - self.spring_stiffness * ((q[1] - q[0]) - 2.0 * self.deflection)

    def deflections(self, q):
        return q

    def accelerations(self, q, v, membrane_forces, payload: PayloadLaw):
        fp = self.spring_force(q)
        # Elementwise over the two disks, not two scalars stacked: XLA fuses a whole stage of
        # the vector field into the stack, and on one CPU device it emitted that fusion as a
        # scalar loop calling a non-inlined function per element (the step's costliest
        # kernel; bench/NOTES.md)
        on_b = jnp.arange(2) == 1
        load = jnp.where(on_b, payload.force(q[1], v[1]), 0.0)
        mass = jnp.where(on_b, self.disk_mass + payload.mass, self.disk_mass)
        return (membrane_forces + jnp.where(on_b, fp, -fp) - load) / mass

    def static_forces(self, q):
        f = self.membrane.static_force(q)
        fp = self.spring_force(q)
        return jnp.stack([f[0] - fp, f[1] + fp])

    def static_guess(self):
        return jnp.array([-0.5, 0.5]) * self.deflection
