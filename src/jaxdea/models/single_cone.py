"""SCDEA-LS: single cone DEA biased by a linear compression spring (paper 000, config I)."""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ..membrane import ConeMembrane
from ..payloads import PayloadLaw
from .cone import ConeActuator


class SCDEA_LS(ConeActuator):
    """Single cone + linear spring + payload (paper 000 eq 16).

    ``(m + M) d'' = F_DEA(d) + F_p - c d'`` with ``F_p = F0 - k (d - d0)``. Table S.I (the
    biasing forces) is missing from the paper: the spring is tuned, as the paper says, so the
    relaxed unactuated cone rests at ``d0``, i.e. the preload is ``F0 = -F_DEA(d0)`` of the
    relaxed, uncharged membrane (reference/cone_power.md item 9). Its one membrane is "A".
    """

    membrane: ConeMembrane
    disk_mass: ArrayLike
    spring_stiffness: ArrayLike
    deflection: ArrayLike

    n_dof: ClassVar[int] = 1
    membrane_names: ClassVar[tuple[str, ...]] = ("A",)
    payload_dof: ClassVar[int] = 0
    name: ClassVar[str] = "scdea_ls"

    @property
    def preload(self) -> Array:
        """Spring preload ``F0`` that puts the relaxed, unactuated cone at ``d0`` (N)."""
        return -self.membrane.static_force(self.deflection)

    def spring_force(self, q: Array) -> Array:
        return self.preload - self.spring_stiffness * (q - self.deflection)

    def deflections(self, q):
        return q

    def accelerations(self, q, v, membrane_forces, payload: PayloadLaw):
        force = membrane_forces + self.spring_force(q) - payload.force(q, v)
        return force / (self.disk_mass + payload.mass)

    def static_forces(self, q):
        return self.membrane.static_force(q) + self.spring_force(q)

    def static_guess(self):
        return jnp.full((1,), 0.5) * self.deflection
