"""Conical DEA with a biasing mass: paper 002 (Huang, Ye, Wang 2020) with membrane inertia,
and paper 001's (Nouhi thesis) generalized-Kelvin variant.

A membrane of thickness ``d0`` spans a frame (radius ``R``) and a central plate (radius
``R0``); the weight pulls the plate down by ``z1`` (prestretched state) and the voltage adds
``z2`` (electro-deformed state). Homogeneous generatrix stretch ``lam = L2/L0 =
sqrt((z1+z2)^2 + L0^2)/L0`` (002 eqs 3-5; :func:`jaxdea.geometry.cone_kinematics`),
circumferential stretch 1, thickness stretch ``1/lam`` (eq 6).

Equation of motion (eq 24, rebuilt -- its extraction is garbled -- from eqs 15, 16, 19-22):

    M(lam) lam'' = k L0^2 lam lam'^2 / (lam^2-1)^2 + F_P(lam) + eps Phi^2 lam / d0^2 - S
    M(lam) = k L0^2 lam^2 / (lam^2 - 1),   k = rho (R + 3 R0) / (6 (R + R0)) [+ m_add / V0]
    F_P(lam) = P lam / (pi d0 (R + R0) sqrt(lam^2 - 1))
    S = dW_s/dlam  (eq 19-20: the elastic energy density's derivative)

- ``eps Phi^2 lam/d0^2``: eq 15's ``2 eps Phi^2 lam/d0^2`` less the derivative of the
  ``D^2/(2 eps) = eps Phi^2 lam^2/(2 d0^2)`` part of W (eq 20);
- the ``lam'^2`` term and ``M``: eq 15's inertia term with ``z2''`` from eq 16, whose printed
  exponent 2 on ``(L2^2 - L0^2)`` must be 3/2 (``z = L0 sqrt(lam^2-1)`` differentiated twice);
  the rebuilt form agrees with the legible first line of eq 24;
- ``m_add`` (``added_mass``): inertia of the weight, absent from 002 eq 13 (the paper keeps
  only the membrane's inertia, eq 12); 0 reproduces the paper.

Materials (both in :mod:`jaxdea.materials`):

- :class:`GentSpringDashpot` with ``flow="conjugate"`` (paper 002): tracked stretches
  ``(l1, l2) = (lam, 1/lam)`` (generatrix, thickness; the circumferential stretch is the
  dependent one), state ``(xi1, xi2)`` per unit as in eq 19. ``S = (sigma_1 - sigma_2)/lam``
  summed over springs (derivative of eq 20), eq 22 for the dashpots.
- :class:`GentKelvinChain` (paper 001): state ``xi`` of the Kelvin elements;
  ``S = sigma/lam`` with ``sigma = s(lam / prod xi)`` the chain stress (thesis eqs 25-31).

State ``(lam, lam_dot, internal)``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike

from ..geometry import cone_kinematics
from ..materials import EPS0, GentKelvinChain, GentSpringDashpot, gent_denominator

__all__ = ["MassCone", "huang2020", "nouhi_kelvin", "prestretch_report",
           "HUANG2020_TABLE1", "NOUHI_TABLE2"]

VELOCITY_SCALE = 1e-3  #: s, weight of the stretch rate in :meth:`MassCone.error_norm`
G = 9.81  #: gravity, m/s^2 (paper 001 uses 9.8: P = 0.21 kg * 9.8 = 2.058 N)


class MassCone(eqx.Module):
    """Biasing-mass cone DEA (SI fields). ``z1`` is the measured prestretch deflection (m);
    ``load`` the static load ``P`` (N) of eq 13; ``eps`` the permittivity (F/m); ``rho`` the
    membrane density (kg/m^3); ``added_mass`` (kg) extra inertia at the plate (0 = paper)."""

    R: ArrayLike
    R0: ArrayLike
    d0: ArrayLike
    eps: ArrayLike
    rho: ArrayLike
    z1: ArrayLike
    load: ArrayLike
    added_mass: ArrayLike
    material: GentSpringDashpot | GentKelvinChain

    # --- geometry -----------------------------------------------------------------------
    @property
    def L0(self) -> Array:
        return self.R - self.R0

    @property
    def volume(self) -> Array:
        """Reference membrane volume ``V0 = pi d0 (R^2 - R0^2)`` (eq 1)."""
        return jnp.pi * self.d0 * (self.R ** 2 - self.R0 ** 2)

    @property
    def lam_pre(self) -> Array:
        """Prestretch ``lam_pre,L = L1/L0`` from the measured ``z1`` (eq 4)."""
        return cone_kinematics(self.z1, self.R0, self.R)[0]

    def deflection(self, lam: ArrayLike) -> Array:
        """Total plate deflection ``z1 + z2 = L0 sqrt(lam^2 - 1)`` (eq 3), m."""
        return self.L0 * jnp.sqrt(lam * lam - 1.0)

    # --- constitutive -------------------------------------------------------------------
    def elastic_force(self, lam: ArrayLike, internal) -> Array:
        """``S = dW_s/dlam`` (Pa): eq 19-20 (002) or the Kelvin chain (001)."""
        m = self.material
        if isinstance(m, GentKelvinChain):
            return m.stress(lam, internal, 1.0) / lam
        xi1, xi2 = internal
        s1, s2 = m.stresses(lam, 1.0 / lam, xi1, xi2)
        return (s1 - s2) / lam

    def internal_rates(self, lam: ArrayLike, internal):
        m = self.material
        if isinstance(m, GentKelvinChain):
            return m.rates(lam, internal, 1.0)
        xi1, xi2 = internal
        return m.dashpot_rates(lam, 1.0 / lam, xi1, xi2)

    def relaxed_internal(self, lam: ArrayLike):
        """Internal state at rest at ``lam``: 002's dashpots relaxed (``xi1 = lam``,
        ``xi2 = 1/lam``); 001's Kelvin elements undeformed (``xi = 1``: the whole prestretch in
        the dashpot-free spring, thesis eqs 33-34 and x0 of its Table 1)."""
        m = self.material
        n = jnp.shape(m.mu)[-1]
        lam = jnp.asarray(lam, float)
        if isinstance(m, GentKelvinChain):
            return jnp.ones(n)
        return lam * jnp.ones(n), jnp.ones(n) / lam

    def load_term(self, lam: ArrayLike, P: ArrayLike | None = None) -> Array:
        """``F_P = P lam / (pi d0 (R+R0) sqrt(lam^2-1))`` (eq 15 / 24), Pa."""
        P = self.load if P is None else P
        return P * lam / (jnp.pi * self.d0 * (self.R + self.R0) * jnp.sqrt(lam * lam - 1.0))

    def equilibrium_load(self) -> Array:
        """The load ``P`` (N) that holds the relaxed membrane at ``lam_pre`` with Phi = 0
        (eq 24 at rest; = thesis eq 34 for the Kelvin chain)."""
        lam = self.lam_pre
        S = self.elastic_force(lam, self.relaxed_internal(lam))
        return S * jnp.pi * self.d0 * (self.R + self.R0) * jnp.sqrt(lam * lam - 1.0) / lam

    # --- dynamics -----------------------------------------------------------------------
    def inertia_coefficient(self) -> Array:
        """``k = rho (R + 3 R0) / (6 (R + R0)) + m_add / V0`` (eqs 12-14), kg/m^3."""
        return (self.rho * (self.R + 3.0 * self.R0) / (6.0 * (self.R + self.R0))
                + self.added_mass / self.volume)

    def error_norm(self, err) -> Array:
        """Step-size/Newton error norm: RMS over the state with the stretch rate weighed by
        ``VELOCITY_SCALE`` (s), i.e. counted as the stretch it moves in that time. Unweighted,
        the membrane-inertia mode (~540 Hz, damping ratio ~0.03) limits the steps to ~0.3 ms
        though it is not excited (see :mod:`jaxdea.viscoelastic`)."""
        lam, v, internal = err
        return optx.rms_norm((lam, VELOCITY_SCALE * v, internal))

    def initial_state(self):
        lam = jnp.asarray(self.lam_pre, float)
        return lam, jnp.zeros_like(lam), self.relaxed_internal(lam)

    def vector_field(self, t, y, signal):
        """Rebuilt eq 24 (module docstring) + eq 22 (002) or eq 31 (001)."""
        lam, v, internal = y
        phi = signal(t)
        a = lam * lam - 1.0
        kl2 = self.inertia_coefficient() * self.L0 ** 2
        rhs = (kl2 * lam * v * v / (a * a) + self.load_term(lam)
               + self.eps * phi * phi * lam / self.d0 ** 2 - self.elastic_force(lam, internal))
        acc = rhs * a / (kl2 * lam * lam)
        return v, acc, self.internal_rates(lam, internal)

    def observables(self, t, y, signal) -> dict:
        lam, v, _ = y
        return {
            "voltage": signal(t),
            "displacement": self.deflection(lam) - self.deflection(self.lam_pre),
            "lam1": lam,
            "lam2": 1.0 / lam,  # thickness stretch (eq 5's lambda_2)
        }

    def check(self) -> None:
        """Raise ``ValueError`` naming the field for out-of-range parameters (non-positive
        relaxation time, Gent limit below the stretch invariant at the prestretch, ...)."""
        for name in ("R", "R0", "d0", "eps", "rho"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name} = {float(getattr(self, name))!r} must be > 0 "
                                 f"(allowed range (0, inf))")
        if not float(self.R) > float(self.R0):
            raise ValueError(f"R = {float(self.R):g} m (frame radius) must exceed R0 = "
                             f"{float(self.R0):g} m (plate radius); allowed range "
                             f"({float(self.R0):g}, inf) m")
        if not float(self.z1) > 0:
            raise ValueError(f"z1 = {float(self.z1)!r} m must be > 0 (allowed range (0, inf))")
        m = self.material
        kelvin = isinstance(m, GentKelvinChain)
        names = ("mu", "J", "eta") if kelvin else ("mu", "J", "tau")
        for name in names:
            for i, val in enumerate(np.atleast_1d(np.asarray(getattr(m, name)))):
                if not (math.isfinite(float(val)) and float(val) > 0):
                    what = " (relaxation times must be positive)" if name in ("tau", "eta") else ""
                    raise ValueError(f"material.{name}[{i}] = {float(val)!r} must be > 0, "
                                     f"allowed range (0, inf){what}")
        lam = float(self.lam_pre)
        if kelvin:
            checks = {"material.J1": (m.mu1, m.J1, lam, 1.0)}
        else:
            checks = {"material.J0": (m.mu0, m.J0, lam, 1.0 / lam)}
        for name, (mu, J, l1, l2) in checks.items():
            if not float(mu) > 0:
                raise ValueError(f"{name.replace('J', 'mu')} = {float(mu)!r} must be > 0")
            inv = float(J * (1.0 - gent_denominator(l1, l2, J)))
            if not float(J) > inv:
                raise ValueError(f"{name} = {float(J):g} is below the stretch invariant I1 - 3 "
                                 f"= {inv:.4g} at the prestretch (Gent lock-up); allowed range "
                                 f"({inv:.4g}, inf)")


#: Paper 002 Table 1: mu_i (Pa), J_i, T_i (s); i = 0 is the equilibrium spring.
HUANG2020_TABLE1 = {
    "mu0": 0.1e3, "J0": 6.8e7,
    "mu": [5277.4e3, 0.1e3, 33.1e3, 571.2e3],
    "J": [79.9e7, 80.1e7, 7.9e7, 3.7e7],
    "tau": [0.01, 3945.71, 9.82, 8484.73],
}

#: Paper 001 Table 2: mu (Pa), J, eta (Pa s); i = 1 has no dashpot.
NOUHI_TABLE2 = {
    "mu1": 3.149e5, "J1": 3.109e4,
    "mu": [5.552e6, 5.232e8, 100.0, 1.573e5],
    "J": [1.016e6, 7.817e6, 7.927e6, 2.0],
    "eta": [555.205, 5.232e4, 8.103e7, 1.573e5],
}


def huang2020(*, load: str = "equilibrium", eps_r: float = 4.7, rho: float = 1000.0,
              added_mass: float = 0.0, mass: float = 0.2) -> MassCone:
    """Paper 002's cone with Table 1. ``load="equilibrium"`` (default, adopted): ``P`` holds
    the relaxed Table-1 membrane at the measured z1 = 1.26 cm; ``load="weight"``:
    ``P = mass g`` (Table 1 cannot hold that at z1: see :func:`prestretch_report`).
    ``eps_r`` (4.7, from paper 001) and ``rho`` (1000 kg/m^3) are chosen: 002 prints neither.
    """
    t = HUANG2020_TABLE1
    mat = GentSpringDashpot(mu0=jnp.asarray(t["mu0"]), J0=jnp.asarray(t["J0"]),
                            mu=jnp.asarray(t["mu"]), J=jnp.asarray(t["J"]),
                            tau=jnp.asarray(t["tau"]), flow="conjugate")
    return with_load(MassCone(R=jnp.asarray(0.06), R0=jnp.asarray(0.03), d0=jnp.asarray(200e-6),
                               eps=jnp.asarray(eps_r * EPS0), rho=jnp.asarray(rho),
                               z1=jnp.asarray(0.0126), load=jnp.asarray(0.0),
                               added_mass=jnp.asarray(added_mass), material=mat),
                      load, mass, G)


def nouhi_kelvin(*, load: str = "equilibrium", eps_r: float = 4.7, rho: float = 1000.0,
                 added_mass: float = 0.0, mass: float = 0.21) -> MassCone:
    """Paper 001's cone (Table 1: frame 6 cm, plate 3 cm -- its a/b are swapped --, h0 =
    200 um, d1 = 12.56 mm, m = 0.21 kg, P = 2.058 N) with the Kelvin chain of Table 2."""
    t = NOUHI_TABLE2
    mat = GentKelvinChain(mu1=jnp.asarray(t["mu1"]), J1=jnp.asarray(t["J1"]),
                          mu=jnp.asarray(t["mu"]), J=jnp.asarray(t["J"]),
                          eta=jnp.asarray(t["eta"]))
    return with_load(MassCone(R=jnp.asarray(0.06), R0=jnp.asarray(0.03), d0=jnp.asarray(200e-6),
                               eps=jnp.asarray(eps_r * EPS0), rho=jnp.asarray(rho),
                               z1=jnp.asarray(0.01256), load=jnp.asarray(0.0),
                               added_mass=jnp.asarray(added_mass), material=mat),
                      load, mass, 9.8)


def with_load(cone: MassCone, load: str, mass: float, g: float) -> MassCone:
    if load == "equilibrium":
        P = cone.equilibrium_load()
    elif load == "weight":
        P = jnp.asarray(mass * g)
    else:
        raise ValueError(f"load must be 'equilibrium' or 'weight', got {load!r}")
    return eqx.tree_at(lambda c: c.load, cone, jnp.asarray(P, float))


def _static_z(cone: MassCone, P: float, S_of_lam) -> float:
    """Deflection (m) where ``F_P(lam) = S(lam)`` by bisection on ``lam`` in (1, 1e3)."""
    def g(lam):
        return float(cone.load_term(lam, P) - S_of_lam(lam))
    lo, hi = 1.0 + 1e-12, 1e3
    if g(hi) > 0:
        return math.inf
    for _ in range(200):
        mid = math.sqrt(lo * hi) if hi / lo > 1.5 else 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 0 else (lo, mid)
    return float(cone.deflection(0.5 * (lo + hi)))


def prestretch_report(cone: MassCone, mass: float, g: float = G) -> dict:
    """Static deflection ``z1`` (m) of the Table-1 membrane under the weight ``mass g``:

    - ``z1_instant``: every spring acting from the flat state (dashpots not yet moved);
    - ``z1_fast_relaxed``: the units with ``tau < 1 s`` relaxed (as after the weight settles);
    - ``z1_relaxed``: all dashpots relaxed (only the equilibrium spring), ``inf`` if none;
    - ``P_weight`` = ``mass g`` vs ``P_equilibrium``: the load that holds the relaxed
      membrane at the measured z1 (:meth:`MassCone.equilibrium_load`).
    Only for :class:`GentSpringDashpot` cones (paper 002). Not differentiable.
    """
    m = cone.material
    P = mass * g
    mu = np.asarray(m.mu)
    tau = np.asarray(m.tau)

    def springs(mask):
        def S(lam):
            s1, s2 = m.equilibrium_stresses(lam, 1.0 / lam)
            b1, b2 = m.branch_stresses(lam, 1.0 / lam, jnp.ones_like(m.mu), jnp.ones_like(m.mu))
            return float((s1 - s2 + jnp.sum(jnp.where(mask, b1 - b2, 0.0))) / lam)
        return S

    return {
        "z1_measured": float(cone.z1),
        "z1_instant": _static_z(cone, P, springs(np.ones_like(mu, bool))),
        "z1_fast_relaxed": _static_z(cone, P, springs(tau >= 1.0)),
        "z1_relaxed": _static_z(cone, P, springs(np.zeros_like(mu, bool))),
        "P_weight": P,
        "P_equilibrium": float(cone.equilibrium_load()),
    }
