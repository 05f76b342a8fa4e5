"""What every cone actuator shares: state layout, vector field, stiff linearisation, statics.

A configuration (single cone, double cones) only says how its membranes sit on its degrees of
freedom (:meth:`ConeActuator.deflections`), how forces accelerate those degrees of freedom
(:meth:`ConeActuator.accelerations`) and where it rests (:meth:`ConeActuator.static_forces`).
Everything else — membrane law, RC charging, energy bookkeeping — is written once here.
"""

from __future__ import annotations

import abc
import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ..electrical import charge_rate
from ..membrane import BREAKDOWN_FIELD, ConeMembrane
from ..payloads import PayloadLaw
from ..signals import SquareWave
from ..solver import Linearisation, exp_decay_weights, phi_functions


def hermite_coefficients(x0, v0, x1, v1, h):
    """Cubic Hermite interpolation on one step.

    **Arguments:**

    - `x0`, `v0`: value and derivative at ``s = 0``.
    - `x1`, `v1`: value and derivative at ``s = h``.
    - `h`: the step length.

    **Returns:**

    ``(a, b)`` of the cubic ``x0 + v0 s + a s^2 + b s^3`` matching x, x' at 0 and h.
    """
    a = (3.0 * (x1 - x0) / h - 2.0 * v0 - v1) / h
    b = (v0 + v1 - 2.0 * (x1 - x0) / h) / (h * h)
    return a, b


#: Safeguarded Newton iterations for the current's zero in a step (``returned_charge``).
_RC_NEWTON = 3


def returned_charge(q0, i0, q1, i1, h, kappa, q_inf):
    """Integral over one step of ``min(i, 0)``: charge pushed back into the source.

    Within a step the charge relaxes exactly like ``q_inf + (q0 - q_inf) exp(-kappa s)``
    (frozen RC part) plus a smooth remainder; the remainder is the cubic Hermite interpolant
    that matches ``q`` and ``i = q'`` at both ends. Splitting off the exponential keeps this
    exact for the ~49 us charging transient even when a step spans several RC time constants.

    The negative part is integrated in closed form: where the current changes sign over the
    step, its zero is found in the half whose ends differ in sign by regula falsi and then
    ``_RC_NEWTON`` safeguarded Newton steps (one that leaves the bracket becomes a bisection; on
    the steps of a DCDEA-RR run the zero is within 9e-7 of the step length, and the charge's
    error is second order in that), and the charge on the negative side is the interpolant's own
    antiderivative up to or from the zero. The result is continuously differentiable in the step
    data: a zero that leaves through an end of the step takes a vanishing charge with it, and
    the zero's position enters only through ``Q(r)``, whose slope ``i(r)`` is zero (so the
    iteration is not differentiated). A quadrature of ``min(i, 0)`` had a kink each time one
    node's current changed sign, which made P_in's derivatives step-size dependent at the 1e-4
    level (issue 14). A dip through zero and back within one step (both ends of one sign) is not
    resolved; its charge vanishes like the dip's depth to the power 3/2, so that is continuously
    differentiable too, and the steps (tens per RC transient, hundreds per period) keep such
    dips rare and shallow.

    **Arguments:**

    - `q0`, `i0`: charge and current at the start of the step.
    - `q1`, `i1`: charge and current at its end.
    - `h`: the step, s.
    - `kappa`: RC relaxation rate frozen at the start, 1/s.
    - `q_inf`: the charge the source would settle to (``C Phi``).

    **Returns:**

    The returned charge (<= 0), with the shape of ``q0``.
    """
    z0 = q0 - q_inf
    decay_h = jnp.exp(-kappa * h)
    dr0 = i0 + kappa * z0
    a, b = hermite_coefficients(0.0, dr0, q1 - q_inf - z0 * decay_h, i1 + kappa * z0 * decay_h, h)

    def current(s):  # i(s), its slope, and the charge moved since s = 0
        e = jnp.exp(-kappa * s)
        return (-kappa * z0 * e + dr0 + s * (2.0 * a + 3.0 * b * s),
                kappa * kappa * z0 * e + 2.0 * a + 6.0 * b * s,
                z0 * (e - 1.0) + s * (dr0 + s * (a + b * s)))

    neg0, neg1 = i0 < 0.0, i1 < 0.0
    cross = neg0 != neg1

    def zero():  # bracket by the midpoint's sign, regula falsi, then safeguarded Newton
        half = 0.5 * h
        im = current(half)[0]
        first = (im < 0.0) != neg0  # the midpoint is past the zero
        lo, hi = jnp.where(first, 0.0, half), jnp.where(first, half, h)
        flo, fhi = jnp.where(first, i0, im), jnp.where(first, im, i1)
        den = jnp.where(cross, flo - fhi, 1.0)
        r = lo + (hi - lo) * jnp.clip(jnp.where(den != 0.0, flo / den, 0.5), 0.0, 1.0)
        for _ in range(_RC_NEWTON):
            ir, di, _ = current(r)
            right = (ir < 0.0) == neg0  # the zero lies right of r
            lo, hi = jnp.where(right, r, lo), jnp.where(right, hi, r)
            ok = cross & (di != 0.0)
            step = r - ir / jnp.where(ok, di, 1.0)
            r = jnp.where(ok & (step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
        return r

    r = jax.lax.stop_gradient(zero())
    moved = current(r)[2]  # the charge from s = 0 to the zero
    total = q1 - q0
    back = jnp.where(neg0 & neg1, total,
                     jnp.where(cross, jnp.where(neg0, moved, total - moved), 0.0))
    return jnp.minimum(back, 0.0)


def solve_small(a: Array, b: Array) -> Array:
    """``a^-1 b`` for the 1 x 1 and 2 x 2 systems of the cone models in closed form (else
    ``jnp.linalg.solve``). Not a LAPACK call: vmapped over designs inside a program split
    over devices, a batched LAPACK solve splits its batch over XLA's intra-op thread pool and
    can deadlock it (``jaxdea.engine.periodic.newton_step``)."""
    n = b.shape[-1]
    if n == 1:
        return b / a[..., 0]
    if n == 2:
        det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
        return jnp.stack([b[..., 0] * a[..., 1, 1] - a[..., 0, 1] * b[..., 1],
                          a[..., 0, 0] * b[..., 1] - a[..., 1, 0] * b[..., 0]], -1) / det[
                              ..., None]
    return jnp.linalg.solve(a, b)


class ConeState(eqx.Module):
    """State of a cone actuator + payload. Leaves have shape (n_dof,), (n_membranes,) or ().

    The last three fields are energy accumulators (time integrals), so cycle averages need no
    stored trajectory (DESIGN: power as extra ODE states). The energy the source gets back
    when current flows against it (for P_in without recovery) is not a state: its integrand
    ``min(Phi i, 0)`` is only known accurately at step ends, so the lane engine integrates it
    step by step (:meth:`ConeActuator.returned_energy`).
    """

    q: Array  #: disk positions (signed deflections of the dofs), m
    v: Array  #: disk velocities, m/s
    charge: Array  #: charge on each membrane, C
    xi_m: Array  #: dielectric dashpot stretch of each membrane
    xi_el: Array  #: electrode dashpot stretch of each membrane
    payload_work: Array  #: integral of the payload's dissipated power dt (f(v) v), J
    v2: Array  #: integral of v_payload^2 dt, m^2/s
    energy_in: Array  #: integral of Phi_in i dt per membrane (signed), J


class Loading(eqx.Module):
    """Everything outside the actuator: the drive voltages and the payload."""

    drive: SquareWave
    payload: PayloadLaw


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
                      payload: PayloadLaw) -> Array:
        """Equations of motion (paper 000 eqs 16-18): ``q''`` from the membrane forces."""

    @abc.abstractmethod
    def static_forces(self, q: Array) -> Array:
        """Net force on each dof at rest: uncharged, dashpots relaxed, no payload force."""

    @abc.abstractmethod
    def static_guess(self) -> Array:
        """A starting point for the static-equilibrium Newton solve (not the answer)."""

    # --- shared -----------------------------------------------------------------------------
    def equilibrium(self, iterations: int = 40, payload: PayloadLaw | None = None) -> Array:
        """Static equilibrium positions at zero voltage, by Newton's method on
        :meth:`static_forces` (differentiable; fixed iteration count so it jits and vmaps).

        With a ``payload`` that loads the disk at rest (``payload.loads_at_rest``: a weight,
        a preloaded spring) its force at zero velocity is included; the Newton solve then
        starts from the equilibrium without it."""

        def solve(forces, q):
            def newton(_, q):
                jac = jax.jacfwd(forces)(q)
                return q - solve_small(jac, forces(q))

            return jax.lax.fori_loop(0, iterations, newton, q)

        q = solve(self.static_forces, self.static_guess())
        if payload is None or not payload.loads_at_rest:
            return q
        unit = jnp.zeros(self.n_dof, q.dtype).at[self.payload_dof].set(1.0)
        x = lambda q: q[self.payload_dof]  # noqa: E731
        return solve(lambda q: self.static_forces(q) - unit * payload.force(
            x(q), jnp.zeros_like(x(q))), q)

    def rest_position(self) -> Array:
        """The payload dof's position at the zero-voltage equilibrium without payload, m
        (where an :class:`~jaxdea.Elastic` load without ``anchor`` is anchored)."""
        return self.equilibrium()[self.payload_dof]

    def initial_state(self, payload: PayloadLaw | None = None) -> ConeState:
        """At rest at the static equilibrium (with ``payload``'s force at rest, if any),
        uncharged, Maxwell branches relaxed."""
        q = self.equilibrium(payload=payload)
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
        phi = args.drive(t).astype(y.charge.dtype)  # single-precision lanes stay single
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
            payload_work=args.payload.dissipated_power(vp),
            v2=vp * vp,
            energy_in=power_in,
        )

    def linearisation(self, t, y: ConeState, args: Loading) -> Linearisation:
        """Stiff RC part frozen at the current geometry (for :mod:`jaxdea.solver`'s solvers)."""
        d = self.deflections(y.q)
        return ChargeLinearisation(
            template=y,
            kappa=self.membrane.charge_relaxation_rate(d),
            phi=args.drive(t).astype(y.charge.dtype),
            two_rs=2.0 * self.membrane.electrode_resistance,
        )

    # --- per-step diagnostics of the lane engine ---------------------------------------------
    def payload_motion(self, y: ConeState) -> tuple[Array, Array]:
        """Payload position and velocity of state ``y`` (the Hermite data of the amplitude).

        **Returns:**

        ``(x, v)`` of the payload dof, m and m/s.
        """
        i = self.payload_dof
        return y.q[i], y.v[i]

    def lockup_margin(self, y: ConeState) -> Array:
        """Smallest Gent lock-up margin over all membranes of state ``y``.

        **Returns:**

        A scalar; the state is locked up (a stretch reached the limiting-chain limit) unless
        it is > 0.
        """
        return jnp.min(self.membrane.gent_margin(self.deflections(y.q), y.xi_m, y.xi_el))

    def returned_energy(self, t0, h, y0: ConeState, y1: ConeState, args: Loading,
                        on=slice(None)) -> Array:
        """Energy pushed back into the sources of membranes ``on`` over one step.

        The source voltage is constant within a step (steps never cross an edge), so this is
        ``Phi`` times :func:`returned_charge` of the step.

        **Arguments:**

        - `t0`, `h`: start and length of the step, s.
        - `y0`, `y1`: the states at its ends.
        - `args`: the loading (drive and payload).
        - `on`: the membranes (a static slice or index array; an undriven membrane has
          ``Phi = 0``: no energy either way).

        **Returns:**

        The returned energy (<= 0) per selected membrane, J.
        """
        mem = self.membrane
        phi = args.drive(t0 + 0.5 * h)[on]
        q0, q1 = y0.charge[on], y1.charge[on]
        cap0 = mem.capacitance(self.deflections(y0.q)[on])
        i0 = charge_rate(phi, q0, cap0, mem.electrode_resistance)
        i1 = mem.current(self.deflections(y1.q)[on], q1, phi)
        kappa0 = 1.0 / (2.0 * mem.electrode_resistance * cap0)
        return phi * returned_charge(q0, i0, q1, i1, h, kappa0, cap0 * phi)

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
        decay, gain = exp_decay_weights(self.kappa, jnp.asarray(h, self.kappa.dtype))
        zq = decay * z.charge
        # Off-phase charge decays geometrically towards 0 and would crawl through the
        # subnormal range (Q^2 in the Maxwell stress goes subnormal below ~1e-150 C), where
        # arithmetic is far slower: flush charges below 1e-100 C (physically nil) to zero.
        zq = jnp.where(jnp.abs(zq) < 1e-100, 0.0, zq)
        out = eqx.tree_at(lambda s: s.charge, z, zq)
        return eqx.tree_at(lambda s: s.energy_in, out, z.energy_in - self.phi * gain * z.charge)

    def phi_k(self, k, h, z):
        """``phi_k(hA) z`` (:func:`jaxdea.solver.phi_functions`): ``phi_k(-kappa h)`` on the
        charge; ``z / k!`` on the states outside the RC mode; on the input energy, driven by
        the charge (``A``'s row ``-phi kappa``), ``z_E / k! + phi (phi_k(-kappa h) - 1/k!) z_Q``
        (the divided difference of ``phi_k`` over ``A``'s eigenvalues ``-kappa`` and 0)."""
        if k == 0:
            return self.flow(h, z)
        a = -jnp.asarray(self.kappa, jnp.float64) * h  # phi_k in float64 whatever the lanes
        pk = phi_functions(a, k)[k].astype(z.charge.dtype)
        fk = 1.0 / math.factorial(k)
        out = jax.tree_util.tree_map(lambda x: fk * x, z)
        out = eqx.tree_at(lambda s: s.charge, out, pk * z.charge)
        return eqx.tree_at(lambda s: s.energy_in, out,
                           fk * z.energy_in + self.phi * (pk - fk) * z.charge)


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
    #: dielectric breakdown field, V/m (checked by the studies, not used by the dynamics)
    breakdown_field: float = eqx.field(static=True, default=BREAKDOWN_FIELD)

    def nominal_field(self) -> Array:
        """The drive's nominal electric field, V/m: ``voltage`` over the thinnest membrane's
        dielectric thickness ``H_m`` at the zero-voltage static equilibrium (eqs 6, 8)."""
        d = self.actuator.deflections(self.actuator.equilibrium())
        return self.voltage / jnp.min(self.actuator.membrane.kinematics(d)[3])
