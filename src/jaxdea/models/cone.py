"""What every cone actuator shares: state layout, vector field, stiff linearisation, statics.

A configuration (single cone, double cones) only says how its membranes sit on its degrees of
freedom (:meth:`ConeActuator.deflections`), how forces accelerate those degrees of freedom
(:meth:`ConeActuator.accelerations`) and where it rests (:meth:`ConeActuator.static_forces`).
Everything else — membrane law, RC charging, energy bookkeeping — is written once here.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ..membrane import ConeMembrane
from ..payloads import LinearViscous
from ..signals import SquareWave
from ..solver import Linearisation, exp_decay_weights


class ConeState(eqx.Module):
    """State of a cone actuator + payload. Leaves have shape (n_dof,), (n_membranes,) or ().

    The last three fields are energy accumulators (time integrals), so cycle averages need no
    stored trajectory (DESIGN: power as extra ODE states). The energy the source gets back
    when current flows against it (for P_in without recovery) is not a state: its integrand
    ``min(Phi i, 0)`` is only known accurately at step ends, so :mod:`jaxdea.protocol`
    integrates it step by step (see there).
    """

    q: Array  #: disk positions (signed deflections of the dofs), m
    v: Array  #: disk velocities, m/s
    charge: Array  #: charge on each membrane, C
    xi_m: Array  #: dielectric dashpot stretch of each membrane
    xi_el: Array  #: electrode dashpot stretch of each membrane
    payload_work: Array  #: integral of f(v) v dt: energy dissipated in the payload, J
    v2: Array  #: integral of v_payload^2 dt, m^2/s
    energy_in: Array  #: integral of Phi_in i dt per membrane (signed), J


class Loading(eqx.Module):
    """Everything outside the actuator: the drive voltages and the payload."""

    drive: SquareWave
    payload: LinearViscous


class ConeActuator(eqx.Module):
    """Base class of the cone configurations of paper 000.

    Subclasses set the class constants and implement the four abstract methods.
    ``membrane`` is shared by all membranes of the actuator (the papers use identical ones);
    ``disk_mass`` is the mass ``m`` of one central disk.
    """

    membrane: eqx.AbstractVar[ConeMembrane]
    disk_mass: eqx.AbstractVar[ArrayLike]

    n_dof: ClassVar[int]
    membrane_names: ClassVar[tuple[str, ...]]
    payload_dof: ClassVar[int]
    name: ClassVar[str]

    @property
    def n_membranes(self) -> int:
        return len(self.membrane_names)

    # --- configuration-specific -------------------------------------------------------------
    @abc.abstractmethod
    def deflections(self, q: Array) -> Array:
        """Signed deflection of each membrane for dof positions ``q``."""

    @abc.abstractmethod
    def accelerations(self, q: Array, v: Array, membrane_forces: Array,
                      payload: LinearViscous) -> Array:
        """Equations of motion (paper 000 eqs 16-18): ``q''`` from the membrane forces."""

    @abc.abstractmethod
    def static_forces(self, q: Array) -> Array:
        """Net force on each dof at rest: uncharged, dashpots relaxed, no payload force."""

    @abc.abstractmethod
    def static_guess(self) -> Array:
        """A starting point for the static-equilibrium Newton solve (not the answer)."""

    # --- shared -----------------------------------------------------------------------------
    def equilibrium(self, iterations: int = 40) -> Array:
        """Static equilibrium positions at zero voltage, by Newton's method on
        :meth:`static_forces` (differentiable; fixed iteration count so it jits and vmaps)."""

        def newton(_, q):
            jac = jax.jacfwd(self.static_forces)(q)
            return q - jnp.linalg.solve(jac, self.static_forces(q))

        return jax.lax.fori_loop(0, iterations, newton, self.static_guess())

    def initial_state(self) -> ConeState:
        """At rest at the static equilibrium, uncharged, Maxwell branches relaxed."""
        q = self.equilibrium()
        d = self.deflections(q)
        xi_m, xi_el = self.membrane.relaxed_dashpots(d)
        zeros = jnp.zeros(self.n_membranes, dtype=q.dtype)
        return ConeState(
            q=q,
            v=jnp.zeros_like(q),
            charge=zeros,
            xi_m=xi_m,
            xi_el=xi_el,
            payload_work=jnp.zeros((), q.dtype),
            v2=jnp.zeros((), q.dtype),
            energy_in=zeros,
        )

    def vector_field(self, t, y: ConeState, args: Loading) -> ConeState:
        """Time derivative of the whole state (mechanics, charges, dashpots, energies)."""
        phi = args.drive(t)
        d = self.deflections(y.q)
        r = self.membrane.respond(d, y.charge, y.xi_m, y.xi_el, phi)
        acc = self.accelerations(y.q, y.v, r.force, args.payload)
        vp = y.v[self.payload_dof]
        power_in = phi * r.current
        return ConeState(
            q=y.v,
            v=acc,
            charge=r.current,
            xi_m=r.dxi_m,
            xi_el=r.dxi_el,
            payload_work=args.payload.resisting_force(vp) * vp,
            v2=vp * vp,
            energy_in=power_in,
        )

    def linearisation(self, t, y: ConeState, args: Loading) -> Linearisation:
        """Stiff RC part frozen at the current geometry (for :class:`jaxdea.solver.LawsonRK4`)."""
        d = self.deflections(y.q)
        return ChargeLinearisation(
            template=y,
            kappa=self.membrane.charge_relaxation_rate(d),
            phi=args.drive(t),
            two_rs=2.0 * self.membrane.electrode_resistance,
        )

    def observables(self, t, y: ConeState, args: Loading) -> dict[str, Array]:
        """Instantaneous quantities for plots and checks (SI units)."""
        phi = args.drive(t)
        d = self.deflections(y.q)
        r = self.membrane.respond(d, y.charge, y.xi_m, y.xi_el, phi)
        return {
            "payload_position": y.q[self.payload_dof],
            "payload_velocity": y.v[self.payload_dof],
            "deflection": d,
            "membrane_force": r.force,
            "current": r.current,
            "dea_voltage": r.voltage,
            "source_voltage": phi,
            "gent_margin": self.membrane.gent_margin(d, y.xi_m, y.xi_el),
        }


class ChargeLinearisation(Linearisation):
    """RC part of a cone frozen at one geometry: ``Q' = -kappa (Q - phi / (kappa 2 R_s))``.

    ``phi / (kappa 2 R_s) = C phi`` is the charge the source would settle to. The signed
    input-energy accumulator is driven by the same mode (``E' = phi i = -phi kappa (Q - C phi)``),
    so it is propagated exactly too: the P_in integral stays exact across the ~49 us charging
    transient after every edge, whatever the step.
    """

    template: ConeState
    kappa: Array
    phi: Array
    two_rs: Array

    @property
    def fixed_point(self):
        zero = jax.tree_util.tree_map(jnp.zeros_like, self.template)
        return eqx.tree_at(lambda s: s.charge, zero, self.phi / (self.kappa * self.two_rs))

    def apply(self, z):
        zero = jax.tree_util.tree_map(jnp.zeros_like, z)
        out = eqx.tree_at(lambda s: s.charge, zero, -self.kappa * z.charge)
        return eqx.tree_at(lambda s: s.energy_in, out, -self.phi * self.kappa * z.charge)

    def flow(self, h, z):
        decay, gain = exp_decay_weights(self.kappa, h)
        zq = decay * z.charge
        # Off-phase charge decays geometrically towards 0 and would crawl through the
        # subnormal range (Q^2 in the Maxwell stress goes subnormal below ~1e-150 C), where
        # arithmetic is far slower: flush charges below 1e-100 C (physically nil) to zero.
        zq = jnp.where(jnp.abs(zq) < 1e-100, 0.0, zq)
        out = eqx.tree_at(lambda s: s.charge, z, zq)
        return eqx.tree_at(lambda s: s.energy_in, out, z.energy_in - self.phi * gain * z.charge)


class Model(eqx.Module):
    """A configured cone DEA: the actuator and its default drive (square-wave voltage, duty).

    What :func:`jaxdea.load_config` returns for the square-wave cones of paper 000, and what
    the cone studies (:func:`jaxdea.sweep`, :func:`jaxdea.powermap`, :func:`jaxdea.simulate`)
    take.
    """

    actuator: ConeActuator
    voltage: Any  #: drive amplitude, V
    duty: Any  #: fraction of the period the voltage is on
    name: str = eqx.field(static=True, default="")
