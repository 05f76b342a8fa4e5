"""Drive voltages.

Paper 000 drives its cones with a unipolar square wave (0 / V0, 50 % duty, "on" in the first
part of each period); double cones may drive both membranes with a relative phase. A drive
evaluates to one source voltage per membrane, and knows where its discontinuities are so the
integrator can put step boundaries on them (DESIGN: never let a controller find edges by
rejection).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


class SquareWave(eqx.Module):
    """Unipolar square wave per membrane: ``amplitude`` while on, 0 while off.

    ``amplitude`` and ``phase`` have one entry per membrane (amplitude 0 = not driven).
    Membrane ``j`` is on while ``frac(f t - phase_j / (2 pi)) < duty``: a positive phase
    delays that membrane's wave by ``phase_j / (2 pi)`` periods (pi = antiphase).
    """

    amplitude: Array
    frequency: ArrayLike
    duty: ArrayLike
    phase: Array

    @property
    def period(self) -> Array:
        return 1.0 / self.frequency

    def cycle_position(self, t: ArrayLike) -> Array:
        """Position of each membrane's wave in its own cycle, in [0, 1)."""
        s = t * self.frequency - self.phase / (2.0 * jnp.pi)
        return s - jnp.floor(s)

    def __call__(self, t: ArrayLike) -> Array:
        on = self.cycle_position(t) < self.duty
        return jnp.where(on, self.amplitude, 0.0)

    def edge_fractions(self) -> Array:
        """Switching instants within one period of membrane A's cycle, as fractions in [0, 1).

        Two per membrane (on and off edge), driven or not; duplicates are harmless.
        """
        on = self.phase / (2.0 * jnp.pi)
        edges = jnp.concatenate([on, on + self.duty])
        return edges - jnp.floor(edges)
