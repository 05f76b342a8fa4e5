"""Payloads driven by the actuator (paper 000's "generalized dissipative payloads", and more).

Paper 000 (Fig 3, eq 19): a mass ``M`` moving against a linear viscous dashpot ``c``,
``f(v) = c v``, horizontal (no gravity). Here a payload is any sum of laws
(``Drag(...) + Elastic(...) + Gravity(...)``), each an equinox Module with

- ``mass``: payload mass, kg (a sum's mass is the sum of its laws' masses; it is added to the
  disk that carries the payload);
- ``force(x, v)``: the force the payload puts on that disk against ``+x`` (N; enters the
  equations of motion, eqs 16-18, as ``- force``), at payload position ``x`` (m, the payload
  dof's signed deflection, ``+x`` towards the payload) and velocity ``v`` (m/s);
- ``dissipated_power(v)``: the power dissipated in the payload's dissipative elements, W
  (integrated over time into :attr:`jaxdea.ConeState.payload_work`; its cycle average is
  ``P_out``). Springs and gravity store energy and give it back: they are not output power.
- ``loads_at_rest``: whether the payload pushes on the disk at rest (``force(x, 0) != 0``
  somewhere): the studies then solve the static equilibrium with the payload on, per cell.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

#: Standard gravity, m/s^2.
STANDARD_GRAVITY = 9.80665

#: Units and descriptions of every payload parameter (the linear dashpot's ``c`` is ``c``).
PARAMETER_UNITS = {
    "c": ("N s/m", "payload damping c"),
    "damping": ("N s/m", "payload damping c"),
    "linear": ("N s/m", "viscous drag coefficient c"),
    "quadratic": ("N s^2/m^2", "quadratic drag coefficient c2"),
    "coulomb": ("N", "Coulomb friction force F_c"),
    "coulomb_velocity": ("m/s", "Coulomb smoothing velocity v_s"),
    "stiffness": ("N/m", "payload spring stiffness k_p"),
    "preload": ("N", "payload spring preload"),
    "anchor": ("m", "payload spring anchor position"),
    "tilt": ("rad", "mounting tilt (0: payload hangs below)"),
    "g": ("m/s^2", "gravitational acceleration"),
}


class PayloadLaw(eqx.Module):
    """Base class of the payload laws: a mass and a force, summable with ``+``.

    Subclasses implement :meth:`_force` and :meth:`dissipated_power`; the studies read their
    scalar parameters as dataclass fields (SI units).
    """

    #: (every law has ``mass``, kg: a field, or for a sum the sum of its laws' masses)

    #: parameters that must be > 0 (the others: >= 0 unless in ``signed_fields``)
    positive_fields: ClassVar[tuple[str, ...]] = ()
    #: parameters that may take any finite value
    signed_fields: ClassVar[tuple[str, ...]] = ()
    #: whether the law pushes on the disk at zero velocity (static equilibrium shifts)
    loads_at_rest: ClassVar[bool] = False

    @abc.abstractmethod
    def _force(self, x: ArrayLike, v: ArrayLike, mass: ArrayLike) -> Array:
        """The law's force against ``+x`` (N); ``mass``: the whole payload's mass, kg."""

    @abc.abstractmethod
    def dissipated_power(self, v: ArrayLike) -> Array:
        """Power dissipated in the law's dissipative elements at velocity ``v``, W (>= 0)."""

    def force(self, x: ArrayLike, v: ArrayLike) -> Array:
        """Force the payload puts on its disk against ``+x``, N.

        **Arguments:**

        - `x`: payload position (the payload dof's signed deflection), m.
        - `v`: payload velocity, m/s.
        """
        return self._force(x, v, self.mass)

    @property
    def laws(self) -> tuple[PayloadLaw, ...]:
        """The laws summed in this payload (itself, for a single law)."""
        return (self,)

    def with_mass(self, mass: ArrayLike) -> PayloadLaw:
        """The same payload with total mass ``mass`` (kg)."""
        return eqx.tree_at(lambda p: p.mass, self, mass)

    def __add__(self, other: PayloadLaw) -> Combined:
        if not isinstance(other, PayloadLaw):
            return NotImplemented
        return Combined(self.laws + other.laws)


class LinearViscous(PayloadLaw):
    """Payload mass ``mass`` (kg) with viscous damping ``damping`` (N s/m).

    **Arguments:**

    - `mass`: payload mass ``M``, kg (>= 0).
    - `damping`: viscous coefficient ``c``, N s/m (>= 0): ``f(v) = c v`` (eq 19).
    """

    mass: ArrayLike
    damping: ArrayLike

    def resisting_force(self, v: ArrayLike) -> Array:
        """Force the payload opposes to motion, ``f(v) = c v`` (eq 19)."""
        return self.damping * v

    def _force(self, x, v, mass):
        return self.resisting_force(v)

    def dissipated_power(self, v: ArrayLike) -> Array:
        """Power dissipated in the dashpot, ``f(v) v = c v^2``, W."""
        return self.resisting_force(v) * v

class Drag(PayloadLaw):
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

    def _force(self, x, v, mass):
        return self.resisting_force(v)

    def dissipated_power(self, v: ArrayLike) -> Array:
        """``f(v) v`` (>= 0), W."""
        return self.resisting_force(v) * v


class Elastic(PayloadLaw):
    """A payload held by a spring to ground: a leg, a fin, an elastic load.

    ``force = preload + k_p (x - anchor)``: a linear spring of stiffness ``k_p`` between the
    payload and ground that pushes against ``+x`` with ``preload`` when the payload is at
    ``anchor``. It stores energy and returns it (no output power); it adds ``k_p`` to the
    actuator's stiffness at the payload, so it raises the resonance, and a preload moves the
    rest state (solved with the payload on). Combine it with a :class:`Drag` for the load's
    losses: ``Drag(M, linear=c) + Elastic(stiffness=k_p)``.

    **Arguments:**

    - `mass`: mass carried with the spring, kg (>= 0; default 0).
    - `stiffness`: spring stiffness ``k_p``, N/m (>= 0).
    - `preload`: the spring's force at ``anchor``, N (any sign; > 0 pushes the payload
      towards the actuator, against ``+x``).
    - `anchor`: payload position at which the spring's force is ``preload``, m (the payload
      dof's signed deflection). ``None`` (default): the actuator's own rest position without
      payload, filled in by the studies, so a spring without preload is relaxed at rest.
    """

    mass: ArrayLike = 0.0
    stiffness: ArrayLike = 0.0
    preload: ArrayLike = 0.0
    anchor: ArrayLike | None = None

    signed_fields: ClassVar[tuple[str, ...]] = ("preload", "anchor")
    loads_at_rest: ClassVar[bool] = True

    def _force(self, x, v, mass):
        if self.anchor is None:
            raise ValueError("Elastic.anchor is not set: the studies set it to the actuator's "
                             "rest position (jaxdea.payloads.anchored)")
        return self.preload + self.stiffness * (x - self.anchor)

    def dissipated_power(self, v: ArrayLike) -> Array:
        """0: a spring dissipates nothing."""
        return jnp.zeros_like(jnp.asarray(v, dtype=float))


class Gravity(PayloadLaw):
    """The payload's weight along the actuator's axis (a vertically mounted actuator).

    ``force = - M g cos(tilt)`` against ``+x``, with ``M`` the whole payload's mass (in a sum:
    every law's mass). ``tilt`` is the angle between ``+x`` (from the actuator towards its
    payload) and the downward vertical: 0 = the payload hangs below the actuator (its weight
    pulls the disk along ``+x``), pi = the payload sits on top, pi/2 = horizontal (paper 000).
    The weight of the actuator's own disks is not included. The rest state is solved with
    the weight on; gravity does no net work over a period (no output power).

    **Arguments:**

    - `mass`: payload mass, kg (>= 0; default 0: in a sum, the other laws carry the mass).
    - `tilt`: mounting angle, rad (any finite value).
    - `g`: gravitational acceleration, m/s^2 (>= 0; default 9.80665).
    """

    mass: ArrayLike = 0.0
    tilt: ArrayLike = 0.0
    g: ArrayLike = STANDARD_GRAVITY

    signed_fields: ClassVar[tuple[str, ...]] = ("tilt",)
    loads_at_rest: ClassVar[bool] = True

    def _force(self, x, v, mass):
        return -mass * self.g * jnp.cos(self.tilt) + jnp.zeros_like(v)

    def dissipated_power(self, v: ArrayLike) -> Array:
        """0: a weight dissipates nothing."""
        return jnp.zeros_like(jnp.asarray(v, dtype=float))


class Combined(PayloadLaw):
    """A sum of payload laws (what ``law + law`` builds): masses, forces and dissipated powers
    add; :class:`Gravity` weighs the whole payload's mass.

    **Arguments:**

    - `parts`: the laws, at most one of each type.
    """

    parts: tuple[PayloadLaw, ...]

    def __check_init__(self):
        kinds = [type(p) for p in self.parts]
        if any(isinstance(p, Combined) for p in self.parts) or len(set(kinds)) < len(kinds):
            raise ValueError("a payload sums at most one law of each type, got "
                             + " + ".join(k.__name__ for k in kinds))

    @property
    def mass(self):
        return sum(p.mass for p in self.parts)

    @property
    def loads_at_rest(self) -> bool:
        return any(p.loads_at_rest for p in self.parts)

    @property
    def laws(self) -> tuple[PayloadLaw, ...]:
        return tuple(self.parts)

    def _force(self, x, v, mass):
        return sum(p._force(x, v, mass) for p in self.parts)

    def dissipated_power(self, v: ArrayLike) -> Array:
        return sum(p.dissipated_power(v) for p in self.parts)

    def with_mass(self, mass: ArrayLike) -> Combined:
        """The same sum with ``mass`` on its first law and none on the others."""
        parts = [self.parts[0].with_mass(mass)]
        parts += [p.with_mass(jnp.zeros_like(jnp.asarray(mass, dtype=float)))
                  for p in self.parts[1:]]
        return Combined(tuple(parts))


def parameters(payload: PayloadLaw) -> dict[str, ArrayLike]:
    """Every parameter of ``payload`` but the masses, ``{field name: value}`` (field names
    are unique: a sum holds at most one law of each type)."""
    return {f.name: getattr(law, f.name) for law in payload.laws
            for f in dataclasses.fields(law) if f.name != "mass"}


def replace_parameters(payload: PayloadLaw, **values) -> PayloadLaw:
    """``payload`` with the named parameters (see :func:`parameters`) replaced."""
    laws = []
    for law in payload.laws:
        own = {k: v for k, v in values.items()
               if k in {f.name for f in dataclasses.fields(law)}}
        laws.append(dataclasses.replace(law, **own) if own else law)
    unknown = set(values) - set(parameters(payload))
    if unknown:
        raise ValueError(f"unknown payload parameters {sorted(unknown)}")
    return laws[0] if not isinstance(payload, Combined) else Combined(tuple(laws))


def anchored(payload: PayloadLaw, rest_position: ArrayLike) -> PayloadLaw:
    """``payload`` with an :class:`Elastic` law's unset ``anchor`` set to ``rest_position``
    (m: the payload's position at the actuator's rest without payload)."""
    if "anchor" in parameters(payload) and parameters(payload)["anchor"] is None:
        return replace_parameters(payload, anchor=rest_position)
    return payload
