"""Dissipative payloads driven by the actuator (paper 000's "generalized dissipative payloads").

Paper 000 (Fig 3, eq 19): a mass ``M`` moving against a linear viscous dashpot ``c``,
``f(v) = c v``. Gravity is neglected (horizontal motion).

Every payload law is an equinox Module with

- ``mass``: the payload mass ``M``, kg (added to the disk that carries the payload);
- ``resisting_force(v)``: the force along the axis the payload opposes to its velocity ``v``
  (N; enters the equations of motion, eqs 16-18, as ``- f(v)``);
- ``dissipated_power(v)``: the power dissipated in the payload's dissipative elements, W
  (integrated over time into :attr:`jaxdea.ConeState.payload_work`; its cycle average is
  ``P_out``).

For purely dissipative laws ``dissipated_power(v) = resisting_force(v) * v``.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


class LinearViscous(eqx.Module):
    """Payload mass ``mass`` (kg) with viscous damping ``damping`` (N s/m).

    **Arguments:**

    - `mass`: payload mass ``M``, kg (>= 0).
    - `damping`: viscous coefficient ``c``, N s/m (>= 0): ``f(v) = c v`` (eq 19).
    """

    mass: ArrayLike
    damping: ArrayLike

    #: parameters that must be > 0 (the others: >= 0), checked by the studies
    positive_fields: ClassVar[tuple[str, ...]] = ()

    def resisting_force(self, v: ArrayLike) -> Array:
        """Force the payload opposes to motion, ``f(v) = c v`` (eq 19)."""
        return self.damping * v

    def dissipated_power(self, v: ArrayLike) -> Array:
        """Power dissipated in the dashpot, ``f(v) v = c v^2``, W."""
        return self.resisting_force(v) * v


class Drag(eqx.Module):
    """A payload mass moving against viscous, quadratic and (smoothed) Coulomb drag.

    ``f(v) = c v + c2 v |v| + F_c tanh(v / v_s)``, all terms opposing the motion, all
    dissipative: ``P_out`` is the mean of ``f(v) v >= 0``.

    The Coulomb (dry-friction) term ``F_c sign(v)`` is smoothed as ``F_c tanh(v / v_s)`` so the
    vector field stays smooth (adaptive steps, ``jax.grad``). Below ``|v| ~ v_s`` the friction
    acts as a stiff viscous damper ``F_c / v_s``: the payload creeps instead of sticking, and
    the steps shrink to about ``(m + M) v_s / F_c`` while the payload reverses. The default
    ``v_s = 1e-3`` m/s is far below the payload speeds of paper 000 (~0.1-1 m/s). Measured on
    SCDEA-LS, drive A, ``M = 2 g``, ``F_c = 0.02`` N (20 cycles from rest, last 5 averaged):
    going from ``v_s = 1e-3`` to ``1e-4`` m/s lowers ``P_out`` by 0.3 % at 30 Hz and changes
    it by 0.02 % at 75 Hz (``tests/test_payloads.py``).

    **Arguments:**

    - `mass`: payload mass ``M``, kg (>= 0).
    - `linear`: viscous coefficient ``c``, N s/m (>= 0).
    - `quadratic`: quadratic (turbulent / aerodynamic) coefficient ``c2``, N s^2/m^2 (>= 0).
    - `coulomb`: dry-friction force ``F_c``, N (>= 0).
    - `coulomb_velocity`: smoothing velocity ``v_s`` of the Coulomb term, m/s (> 0).
    """

    mass: ArrayLike
    linear: ArrayLike = 0.0
    quadratic: ArrayLike = 0.0
    coulomb: ArrayLike = 0.0
    coulomb_velocity: ArrayLike = 1e-3

    positive_fields: ClassVar[tuple[str, ...]] = ("coulomb_velocity",)

    def resisting_force(self, v: ArrayLike) -> Array:
        """``f(v) = c v + c2 v |v| + F_c tanh(v / v_s)``, N."""
        return (self.linear * v + self.quadratic * v * jnp.abs(v)
                + self.coulomb * jnp.tanh(v / self.coulomb_velocity))

    def dissipated_power(self, v: ArrayLike) -> Array:
        """``f(v) v`` (>= 0), W."""
        return self.resisting_force(v) * v
