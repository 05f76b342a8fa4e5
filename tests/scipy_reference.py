"""Independent numpy/scipy reference implementation of the cone-DEA power models.

This module is a plain transcription of the equations in
``shared/reference/cone_power.md`` (paper 000 numbering).  It deliberately does
not import anything from ``jaxdea``: it is meant to be used as a test oracle.

Conventions
-----------
* Signed deflection ``d`` (m), ``+x`` toward the payload.  The single cone and
  membrane B of the double cones sit at ``+d0``; membrane A of the double cones
  sits at ``-d0``.
* ``F_DEA`` is the axial force the membrane exerts on its disk (restoring, odd in d).
* Square-wave drive: unipolar 0 / V0, 50 % duty.  Membrane A is "on" for
  ``t mod T in [0, T/2)``; membrane B is shifted later by ``phase / (2 pi) * T``.

State vectors (the energy accumulators are the last entries):

* ``scdea_ls``: ``[d, v, Q, xi_m, xi_el, Iv2, Ein, Ein+]``
* ``dcdea_rr``: ``[d_B, v_B, Q_A, xi_mA, xi_elA, Q_B, xi_mB, xi_elB,
  Iv2, Ein_A, Ein+_A, Ein_B, Ein+_B]``  (membrane A at ``d_B - L_r``)
* ``dcdea_ls``: ``[d_A, v_A, d_B, v_B, Q_A, xi_mA, xi_elA, Q_B, xi_mB, xi_elB,
  Iv2, Ein_A, Ein+_A, Ein_B, Ein+_B]``

``Iv2`` is the integral of the payload velocity squared, ``Ein`` the integral of
``Phi_in * i`` and ``Ein+`` the integral of ``max(Phi_in * i, 0)`` (i = dQ/dt).
In :func:`reference_metrics` the accumulators are only integrated inside the
averaging window (their rates are switched off before it and the states are
zero at the window start); the rhs from :func:`make_rhs` integrates them
unless it is called with ``accumulate=False``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve

# ---------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------

PARAMS = {
    # geometry / film
    "a": 7.5e-3,
    "b": 15e-3,
    "d0": 4e-3,
    "H_m0": 100e-6,
    "lam_p": 1.2,
    "eps_r": 2.8,
    "eps0": 8.854187817e-12,
    "H_el0": 8e-6,
    # electrical
    "R_s": 1e5,
    "V0": 4.9e3,
    # mechanics
    "k": 600.0,
    "L_r": 8e-3,
    "m": 2.26e-3,
    # membrane (Gent spring A, Maxwell branch B)
    "mu_m_A": 0.47e6,
    "J_m_A": 30.0,
    "mu_m_B": 0.21e6,
    "J_m_B": 30.0,
    "tau_m": 2.0e-3,
    # electrode
    "mu_el_A": 3.5e6,
    "J_el_A": 20.0,
    "mu_el_B": 0.66e6,
    "J_el_B": 20.0,
    "tau_el": 1.5e-3,
}

CONFIGS = ("scdea_ls", "dcdea_rr", "dcdea_ls")

# Typical magnitude of every state component (used to build per-component atol).
_SCALE_MEMBRANE = [1e-7, 1.0, 1.0]  # Q, xi_m, xi_el
_SCALE_ACC = [1e-4, 1e-4, 1e-4]  # Iv2 (m^2/s), Ein, Ein+ (J)


def _params(params=None):
    p = dict(PARAMS)
    if params:
        unknown = set(params) - set(PARAMS)
        if unknown:
            raise KeyError(f"unknown parameter(s): {sorted(unknown)}")
        p.update(params)
    return p


class _Const:
    """Pre-computed scalar constants (fast attribute access in the RHS)."""

    def __init__(self, p):
        self.p = p
        self.a = p["a"]
        self.bma = p["b"] - p["a"]
        self.d0 = p["d0"]
        self.lam_p = p["lam_p"]
        self.H_m0 = p["H_m0"]
        self.H_el0 = p["H_el0"]
        self.eps = p["eps_r"] * p["eps0"]
        self.area = math.pi * (p["b"] ** 2 - p["a"] ** 2)
        self.R2 = 2.0 * p["R_s"]
        self.V0 = p["V0"]
        self.k = p["k"]
        self.L_r = p["L_r"]
        self.m = p["m"]
        self.muA_m, self.JA_m = p["mu_m_A"], p["J_m_A"]
        self.muB_m, self.JB_m = p["mu_m_B"], p["J_m_B"]
        self.muA_el, self.JA_el = p["mu_el_A"], p["J_el_A"]
        self.muB_el, self.JB_el = p["mu_el_B"], p["J_el_B"]
        self.eta_m = p["mu_m_B"] * p["tau_m"]
        self.eta_el = p["mu_el_B"] * p["tau_el"]
        self.F0 = None


# ---------------------------------------------------------------------------
# Constitutive pieces (scalars, plain math)
# ---------------------------------------------------------------------------

def geometry(d, params=None):
    """Eq 1-2: return (lam1', sin(alpha), cos(alpha)) for signed deflection d."""
    p = _params(params)
    return _geometry(d, p["b"] - p["a"])


def _geometry(d, bma):
    r = math.sqrt(d * d + bma * bma)
    return r / bma, d / r, bma / r


def gent_stress(mu, J, l1, l2):
    """Gent stress in direction 1: mu (l1^2 - l1^-2 l2^-2) / (1 - (I1 - 3)/J)."""
    inv = 1.0 / (l1 * l1 * l2 * l2)
    den = 1.0 - (l1 * l1 + l2 * l2 + inv - 3.0) / J
    return mu * (l1 * l1 - inv) / den


def _gent_pair(mu, J, l1, l2):
    """Both principal Gent stresses (s1, s2)."""
    inv = 1.0 / (l1 * l1 * l2 * l2)
    den = 1.0 - (l1 * l1 + l2 * l2 + inv - 3.0) / J
    return mu * (l1 * l1 - inv) / den, mu * (l2 * l2 - inv) / den


def capacitance(d, params=None):
    """Eq 5: C = eps_r eps0 pi (b^2 - a^2) / (H_m cos alpha)."""
    c = _Const(_params(params))
    lam1, _, cos_a = _geometry(d, c.bma)
    H_m = c.H_m0 / (lam1 * c.lam_p * c.lam_p)
    return c.eps * c.area / (H_m * cos_a)


def _membrane(c, d, xi_m, xi_el, Q, phi_in):
    """Everything one membrane needs at signed deflection d.

    Returns (F_DEA, dQ/dt, dxi_m/dt, dxi_el/dt).
    """
    bma = c.bma
    r = math.sqrt(d * d + bma * bma)
    lam1 = r / bma
    sin_a = d / r
    cos_a = bma / r
    lp = c.lam_p
    # membrane stretches and thickness (eq 6, 8)
    lm1 = lam1 * lp
    H_m = c.H_m0 / (lm1 * lp)
    # capacitance (eq 5) and RC charge rate (eq 3-4)
    C = c.eps * c.area / (H_m * cos_a)
    phi = Q / C
    dQ = (phi_in - phi) / c.R2
    # membrane stresses (eq 10-11)
    s_h = gent_stress(c.muA_m, c.JA_m, lm1, lp)
    s1, s2 = _gent_pair(c.muB_m, c.JB_m, lm1 / xi_m, 1.0)
    E = phi / H_m
    sigma_m = s_h + s1 - c.eps * E * E
    dxi_m = xi_m * (s1 - 0.5 * s2) / (3.0 * c.eta_m)
    # electrode stresses (eq 7, 9, 12-13)
    H_el = c.H_el0 / lam1
    se_h = gent_stress(c.muA_el, c.JA_el, lam1, 1.0)
    e1, e2 = _gent_pair(c.muB_el, c.JB_el, lam1 / xi_el, 1.0)
    sigma_el = se_h + e1
    dxi_el = xi_el * (e1 - 0.5 * e2) / (3.0 * c.eta_el)
    # axial force (eq 15)
    F = -2.0 * math.pi * c.a * sin_a * (H_m * sigma_m + 2.0 * H_el * sigma_el)
    return F, dQ, dxi_m, dxi_el


def membrane_force(d, xi_m, xi_el, Q, params=None):
    """Eq 15: axial force F_DEA of one membrane at signed deflection d.

    xi_m / xi_el are the dashpot stretches of the membrane / electrode Maxwell
    branches, Q the charge.  The electrostatic stress uses E = (Q/C)/H_m.
    """
    c = _Const(_params(params))
    return _membrane(c, d, xi_m, xi_el, Q, 0.0)[0]


F_DEA = membrane_force  # alias with the paper's name


def electrostatic_force(d, Q, params=None):
    """Electrostatic part of F_DEA: -2 pi a sin(alpha) H_m (-eps E^2)."""
    c = _Const(_params(params))
    lam1, sin_a, cos_a = _geometry(d, c.bma)
    H_m = c.H_m0 / (lam1 * c.lam_p * c.lam_p)
    C = c.eps * c.area / (H_m * cos_a)
    E = Q / C / H_m
    return 2.0 * math.pi * c.a * sin_a * H_m * c.eps * E * E


def dashpot_rates(d, xi_m, xi_el, params=None):
    """Eq 14: (dxi_m/dt, dxi_el/dt), with (1/xi) dxi/dt = (s_1 - s_2/2)/(3 eta),

    eta = mu_B * tau, l1e = l1/xi, l2e = 1 (membrane l1 = lam1'*lam_p,
    electrode l1 = lam1').
    """
    c = _Const(_params(params))
    _, _, dxm, dxe = _membrane(c, d, xi_m, xi_el, 0.0, 0.0)
    return dxm, dxe


def charge_rate(d, Q, phi_in, params=None):
    """Eq 3: dQ/dt = (Phi_in - Q/C)/(2 R_s)."""
    return (phi_in - Q / capacitance(d, params)) / (2.0 * _params(params)["R_s"])


def relaxed_branches(d, params=None):
    """Dashpot stretches of fully relaxed Maxwell branches at deflection d."""
    p = _params(params)
    lam1 = _geometry(d, p["b"] - p["a"])[0]
    return lam1 * p["lam_p"], lam1


def relaxed_force(d, params=None):
    """F_DEA of an unactuated (Q = 0), fully relaxed membrane at d."""
    xm, xe = relaxed_branches(d, params)
    return membrane_force(d, xm, xe, 0.0, params)


def preload(params=None):
    """F0 = -F_DEA(d0) of the relaxed, unactuated membrane (about 1.52 N)."""
    return -relaxed_force(_params(params)["d0"], params)


# ---------------------------------------------------------------------------
# Static equilibrium and initial state
# ---------------------------------------------------------------------------

def _static_residual(config, x, p, F0, g=None):
    """Net static force on each dof; ``g(x_payload)``: payload force against +x at rest."""
    g = g or (lambda _: 0.0)
    if config == "scdea_ls":
        (d,) = x
        return [relaxed_force(d, p) + F0 - p["k"] * (d - p["d0"]) - g(d)]
    if config == "dcdea_rr":
        (dB,) = x
        return [relaxed_force(dB - p["L_r"], p) + relaxed_force(dB, p) - g(dB)]
    if config == "dcdea_ls":
        dA, dB = x
        Fp = F0 - p["k"] * ((dB - dA) - 2.0 * p["d0"])
        return [relaxed_force(dA, p) - Fp, relaxed_force(dB, p) + Fp - g(dB)]
    raise ValueError(f"unknown config {config!r}")


def static_equilibrium(config, params=None, position_force=None):
    """Static (relaxed, unactuated) positions, found with fsolve.

    position_force: optional payload force g(x) (N, against +x) at the payload's
    position x, included in the balance (a weight, a preloaded spring).

    Returns a dict with 'F0' and the position(s): 'd' (scdea_ls),
    'd_B' and 'd_A' = d_B - L_r (dcdea_rr), 'd_A', 'd_B' (dcdea_ls).
    """
    p = _params(params)
    F0 = preload(p)
    d0 = p["d0"]
    if config == "scdea_ls":
        guess = [1.3 * d0]
    elif config == "dcdea_rr":
        guess = [0.6 * p["L_r"]]
    elif config == "dcdea_ls":
        guess = [-0.7 * d0, 1.3 * d0]
    else:
        raise ValueError(f"unknown config {config!r}")
    if position_force is not None:  # start from the equilibrium without the payload
        free = static_equilibrium(config, p)
        guess = [free["d"]] if config == "scdea_ls" else (
            [free["d_B"]] if config == "dcdea_rr" else [free["d_A"], free["d_B"]])
    sol, info, ier, msg = fsolve(
        lambda x: _static_residual(config, x, p, F0, position_force), guess,
        full_output=True, xtol=1e-14)
    # "not making good progress" at xtol 1e-14 is round-off: accept a balance to 1e-12 N
    if ier != 1 and not np.max(np.abs(info["fvec"])) < 1e-12:
        raise RuntimeError(f"static equilibrium failed: {msg}")
    out = {"F0": F0}
    if config == "scdea_ls":
        out["d"] = float(sol[0])
    elif config == "dcdea_rr":
        out["d_B"] = float(sol[0])
        out["d_A"] = float(sol[0]) - p["L_r"]
    else:
        out["d_A"] = float(sol[0])
        out["d_B"] = float(sol[1])
    return out


def _membrane_init(d, p):
    xm, xe = relaxed_branches(d, p)
    return [0.0, xm, xe]


def initial_state(config, params=None, position_force=None):
    """At rest at the static positions, Q = 0, relaxed branches, zero energies."""
    p = _params(params)
    eq = static_equilibrium(config, p, position_force)
    if config == "scdea_ls":
        y = [eq["d"], 0.0] + _membrane_init(eq["d"], p) + [0.0] * 3
    elif config == "dcdea_rr":
        y = ([eq["d_B"], 0.0] + _membrane_init(eq["d_A"], p)
             + _membrane_init(eq["d_B"], p) + [0.0] * 5)
    else:
        y = ([eq["d_A"], 0.0, eq["d_B"], 0.0] + _membrane_init(eq["d_A"], p)
             + _membrane_init(eq["d_B"], p) + [0.0] * 5)
    return np.array(y, dtype=float)


def state_scales(config):
    """Typical magnitude of every state component (for per-component atol)."""
    if config == "scdea_ls":
        return np.array([1e-3, 1e-2] + _SCALE_MEMBRANE + _SCALE_ACC)
    if config == "dcdea_rr":
        return np.array([1e-3, 1e-2] + 2 * _SCALE_MEMBRANE + [1e-4] * 5)
    if config == "dcdea_ls":
        return np.array([1e-3, 1e-2, 1e-3, 1e-2] + 2 * _SCALE_MEMBRANE
                        + [1e-4] * 5)
    raise ValueError(f"unknown config {config!r}")


# ---------------------------------------------------------------------------
# Drive
# ---------------------------------------------------------------------------

def _check_drive(config, drive):
    if drive not in ("A", "B", "both"):
        raise ValueError(f"drive must be 'A', 'B' or 'both', got {drive!r}")
    if config == "scdea_ls" and drive != "A":
        raise ValueError("scdea_ls has a single membrane: use drive='A'")


def drive_voltages(t, freq, drive="A", phase=0.0, params=None):
    """(Phi_A, Phi_B) of the unipolar 50 % square wave at time t."""
    V0 = _params(params)["V0"]
    T = 1.0 / freq
    phiA = phiB = 0.0
    if drive in ("A", "both"):
        phiA = V0 if (t % T) < 0.5 * T else 0.0
    if drive in ("B", "both"):
        shift = (phase / (2.0 * math.pi)) * T
        phiB = V0 if ((t - shift) % T) < 0.5 * T else 0.0
    return phiA, phiB


def _edges(freq, drive, phase, t_end):
    """Discontinuity times of the drive in (0, t_end)."""
    T = 1.0 / freq
    half = 0.5 * T
    n = int(math.ceil(t_end / half)) + 2
    edges = []
    if drive in ("A", "both"):
        edges += [j * half for j in range(1, n)]
    if drive in ("B", "both"):
        shift = ((phase / (2.0 * math.pi)) * T) % T
        edges += [shift + j * half for j in range(-2, n)]
    return edges


# ---------------------------------------------------------------------------
# Right-hand sides (eqs 16-18)
# ---------------------------------------------------------------------------

def make_rhs(config, mass, damping, params=None, force=None, position_force=None):
    """Return rhs(t, y, phiA, phiB, accumulate=True) for a configuration.

    mass = payload mass M (kg), damping = payload dashpot c (N s/m).
    phiA / phiB are the input voltages (constant between drive edges).
    force: optional payload force law f(v) (N, opposing motion) used instead of
    ``damping * v``; the state then carries one more accumulator at its end,
    the integral of ``f(v) v`` (the payload's dissipated energy).
    position_force: optional conservative payload force g(x) (N, against +x) at
    the payload position x (springs, weight): added to f(v), not to the
    dissipated energy. Either one replaces ``damping * v``.
    """
    p = _params(params)
    c = _Const(p)
    c.F0 = preload(p)
    M = float(mass)
    cd = float(damping)
    if force is not None or position_force is not None:
        force = force or (lambda v: 0.0)
        g = position_force or (lambda x: 0.0)
        _rhs = make_rhs(config, mass, 0.0, params)
        ix, iv, _ = _LAYOUT[config]
        inv_payload_mass = 1.0 / {"scdea_ls": p["m"] + M, "dcdea_rr": 2.0 * p["m"] + M,
                                  "dcdea_ls": p["m"] + M}[config]

        def rhs_force(t, y, phiA=0.0, phiB=0.0, accumulate=True):
            dy = _rhs(t, y[:-1], phiA, phiB, accumulate)
            v = y[iv]
            f = force(v)
            dy[iv] -= (f + g(y[ix])) * inv_payload_mass
            return np.append(dy, f * v if accumulate else 0.0)

        return rhs_force
    m = c.m
    k = c.k
    d0 = c.d0
    F0 = c.F0
    L_r = c.L_r
    mem = _membrane

    if config == "scdea_ls":
        inv_mass = 1.0 / (m + M)

        def rhs(t, y, phiA=0.0, phiB=0.0, accumulate=True):
            d, v, Q, xm, xe = y.tolist()[:5]
            F, dQ, dxm, dxe = mem(c, d, xm, xe, Q, phiA)
            acc = (F + F0 - k * (d - d0) - cd * v) * inv_mass
            if accumulate:
                pw = phiA * dQ
                e = (v * v, pw, pw if pw > 0.0 else 0.0)
            else:
                e = (0.0, 0.0, 0.0)
            return np.array((v, acc, dQ, dxm, dxe) + e)

    elif config == "dcdea_rr":
        inv_mass = 1.0 / (2.0 * m + M)

        def rhs(t, y, phiA=0.0, phiB=0.0, accumulate=True):
            dB, v, QA, xmA, xeA, QB, xmB, xeB = y.tolist()[:8]
            FA, dQA, dxmA, dxeA = mem(c, dB - L_r, xmA, xeA, QA, phiA)
            FB, dQB, dxmB, dxeB = mem(c, dB, xmB, xeB, QB, phiB)
            acc = (FA + FB - cd * v) * inv_mass
            if accumulate:
                pA = phiA * dQA
                pB = phiB * dQB
                e = (v * v, pA, pA if pA > 0.0 else 0.0,
                     pB, pB if pB > 0.0 else 0.0)
            else:
                e = (0.0,) * 5
            return np.array((v, acc, dQA, dxmA, dxeA, dQB, dxmB, dxeB) + e)

    elif config == "dcdea_ls":
        inv_mA = 1.0 / m
        inv_mB = 1.0 / (m + M)

        def rhs(t, y, phiA=0.0, phiB=0.0, accumulate=True):
            dA, vA, dB, vB, QA, xmA, xeA, QB, xmB, xeB = y.tolist()[:10]
            FA, dQA, dxmA, dxeA = mem(c, dA, xmA, xeA, QA, phiA)
            FB, dQB, dxmB, dxeB = mem(c, dB, xmB, xeB, QB, phiB)
            Fp = F0 - k * ((dB - dA) - 2.0 * d0)
            aA = (FA - Fp) * inv_mA
            aB = (FB + Fp - cd * vB) * inv_mB
            if accumulate:
                pA = phiA * dQA
                pB = phiB * dQB
                e = (vB * vB, pA, pA if pA > 0.0 else 0.0,
                     pB, pB if pB > 0.0 else 0.0)
            else:
                e = (0.0,) * 5
            return np.array((vA, aA, vB, aB, dQA, dxmA, dxeA, dQB, dxmB, dxeB)
                            + e)

    else:
        raise ValueError(f"unknown config {config!r}")
    return rhs


# index helpers: (payload position, payload velocity, first accumulator)
_LAYOUT = {
    "scdea_ls": (0, 1, 5),
    "dcdea_rr": (0, 1, 8),
    "dcdea_ls": (2, 3, 10),
}


# ---------------------------------------------------------------------------
# Power metrics
# ---------------------------------------------------------------------------

def simulate(config, mass, damping, freq, drive="A", phase=0.0, cycles=100,
             average=5, rtol=1e-9, atol=None, method="LSODA", params=None,
             points_per_cycle=400, max_step=np.inf, force=None,
             position_force=None):
    """Integrate piecewise between drive edges.

    Returns (y_end, t_window, x_window): the final state (accumulators hold
    the integrals over the last `average` cycles) and the payload
    trajectory sampled at `points_per_cycle` over the averaging window.
    force: optional payload force law f(v) (see :func:`make_rhs`); the last
    state entry is then the integral of f(v) v.
    atol: None -> rtol * state_scales(config); a scalar s -> atol_i =
    s * state_scales(config)[i] (i.e. relative to the component scales);
    an array -> used as is.
    """
    _check_drive(config, drive)
    p = _params(params)
    rhs = make_rhs(config, mass, damping, p, force=force, position_force=position_force)
    y = initial_state(config, p, position_force)
    scales = state_scales(config)
    extra = force is not None or position_force is not None
    if extra:
        y = np.append(y, 0.0)
        scales = np.append(scales, 1e-4)
    if atol is None:
        atol_v = rtol * scales
    elif np.ndim(atol) == 0:
        atol_v = float(atol) * scales
    else:
        atol_v = np.asarray(atol, dtype=float)
    T = 1.0 / freq
    t_end = cycles * T
    t_win = (cycles - average) * T
    V0 = p["V0"]
    shift = ((phase / (2.0 * math.pi)) * T) % T

    # breakpoints: drive edges, window start, end (merge near-duplicates)
    raw = sorted(e for e in _edges(freq, drive, phase, t_end) if 0.0 < e < t_end)
    raw.append(t_win)
    bps = [0.0]
    for b in sorted(raw):
        if b - bps[-1] > 1e-12 * T and t_end - b > 1e-12 * T:
            bps.append(b)
    bps.append(t_end)

    n_win = int(round(points_per_cycle * average))
    grid = t_win + np.arange(n_win + 1) * (T / points_per_cycle)
    grid[-1] = min(grid[-1], t_end)
    ipos, _, iacc = _LAYOUT[config]

    t_samples = []
    x_samples = []
    for t0, t1 in zip(bps[:-1], bps[1:]):
        tm = 0.5 * (t0 + t1)
        phiA = V0 if (drive in ("A", "both") and (tm % T) < 0.5 * T) else 0.0
        phiB = V0 if (drive in ("B", "both")
                      and ((tm - shift) % T) < 0.5 * T) else 0.0
        in_window = t0 >= t_win - 1e-12 * T
        if in_window and abs(t0 - t_win) <= 1e-12 * T:
            y = y.copy()
            y[iacc:] = 0.0
        t_eval = None
        if in_window:
            sel = grid[(grid >= t0) & (grid < t1)]
            t_eval = np.append(sel, t1)  # last point = t1 -> sol.y[:, -1]
        sol = solve_ivp(rhs, (t0, t1), y, method=method, rtol=rtol,
                        atol=atol_v, t_eval=t_eval,
                        args=(phiA, phiB, in_window), max_step=max_step)
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed at t={t0}: {sol.message}")
        if t_eval is not None:
            t_samples.append(sol.t)
            x_samples.append(sol.y[ipos])
        y = sol.y[:, -1].copy()
    t_w = np.concatenate(t_samples) if t_samples else np.empty(0)
    x_w = np.concatenate(x_samples) if x_samples else np.empty(0)
    return y, t_w, x_w


def reference_metrics(config, mass, damping, freq, drive="A", phase=0.0,
                      cycles=100, average=5, rtol=1e-9, atol=None,
                      method="LSODA", params=None, points_per_cycle=400,
                      max_step=np.inf, force=None, position_force=None):
    """Power metrics over the last `average` of `cycles` drive cycles.

    config: 'scdea_ls' | 'dcdea_rr' | 'dcdea_ls'; mass = payload M (kg);
    damping = payload c (N s/m); freq (Hz); drive: 'A' | 'B' | 'both';
    phase: delay of B relative to A in radians (0 in-phase, pi antiphase).

    Returns dict: P_out = c * mean(v^2), P_in = mean(sum max(Phi_in i, 0)),
    P_in_signed, efficiency = P_out / P_in, amplitude = (max - min)/2 of the
    payload displacement (sampled at points_per_cycle), v_rms.
    force: optional payload force law f(v) (N) instead of ``damping * v``
    (pass damping=0); P_out is then mean(f(v) v). position_force: a
    conservative payload force g(x) (see :func:`make_rhs`), not in P_out.
    """
    y, t_w, x_w = simulate(config, mass, damping, freq, drive=drive,
                           phase=phase, cycles=cycles, average=average,
                           rtol=rtol, atol=atol, method=method,
                           params=params, points_per_cycle=points_per_cycle,
                           max_step=max_step, force=force,
                           position_force=position_force)
    _, _, iacc = _LAYOUT[config]
    Tw = average / freq
    extra = force is not None or position_force is not None
    acc = y[iacc:] if not extra else y[iacc:-1]
    mean_v2 = acc[0] / Tw
    e_signed = acc[1::2].sum()
    e_pos = acc[2::2].sum()
    P_out = damping * mean_v2 if not extra else y[-1] / Tw
    P_in = e_pos / Tw
    return {
        "P_out": float(P_out),
        "P_in": float(P_in),
        "P_in_signed": float(e_signed / Tw),
        "efficiency": float(P_out / P_in) if P_in > 0 else float("nan"),
        "amplitude": float(0.5 * (x_w.max() - x_w.min())) if x_w.size else
        float("nan"),
        "v_rms": float(math.sqrt(max(mean_v2, 0.0))),
    }
