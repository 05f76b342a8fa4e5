"""Independent numpy/scipy transcriptions of papers 002, 001 and 004 (test oracles).

Imports nothing from ``jaxdea``. The formulas are typed from the papers' printed forms (with
the reconstructions documented in docs/models.md), in a different algebraic arrangement from
the package (e.g. the printed eq 22/24 expressions instead of the Gent stress helpers), and
paper 004 is solved as a reduced DAE (lam1 from the force constraint P1 by brentq at every
right-hand side) instead of the package's eq-14 ODE, so the two share no code path.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

EPS0 = 8.854187817e-12
TAU_V = 1e-3  #: s; the cone references integrate TAU_V * dlam/dt instead of dlam/dt


# --- drives --------------------------------------------------------------------------------
def multisine(t, a, f):
    """Paper 002 eq 25 typed literally (any number of segments)."""
    a = np.asarray(a, float)
    f = np.asarray(f, float)
    T = np.sum(1.0 / f)
    tm = math.fmod(t, T)
    start = 0.0
    for ai, fi in zip(a, f):
        end = start + 1.0 / fi
        if start <= tm < end:
            return ai * math.sin(fi * math.pi * tm - fi * math.pi * start)
        start = end
    return 0.0


def multisine_kinks(a, f, t_end):
    T = np.sum(1.0 / np.asarray(f))
    ends = np.cumsum(1.0 / np.asarray(f))
    out = [k * T + e for k in range(int(t_end / T) + 1) for e in ends]
    return [x for x in out if 0 < x < t_end]


def vp1(t, peak, period):
    """Triangle 0 -> peak (at T/2) -> 0."""
    s = (t / period) % 1.0
    return peak * (1.0 - abs(2.0 * s - 1.0))


def piecewise_solve(rhs, y0, t_eval, kinks, rtol=1e-10, atol=1e-12, method="Radau"):
    """Integrate across the drive kinks by restarting there (no step straddles a kink)."""
    t_eval = np.asarray(t_eval, float)
    edges = [t_eval[0], *[k for k in sorted(kinks) if t_eval[0] < k < t_eval[-1]], t_eval[-1]]
    out = np.empty((len(t_eval), len(y0)))
    y = np.asarray(y0, float)
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (t_eval >= a) & (t_eval <= b)
        te = np.unique(np.concatenate([t_eval[sel], [b]]))
        sol = solve_ivp(rhs, (a, b), y, method=method, rtol=rtol, atol=atol, t_eval=te)
        assert sol.success, sol.message
        if sel.any():
            out[sel] = sol.y.T[np.searchsorted(te, t_eval[sel])]
        y = sol.y[:, -1]
    return out


# --- paper 004: planar pure-shear DEA (reduced DAE) -----------------------------------------
def gent(l1, l2, mu, J):
    """sigma_1 - sigma_3 of a Gent spring, paper 004 eq 5 terms."""
    i3 = 1.0 / (l1 * l1 * l2 * l2)
    return mu * (l1 * l1 - i3) / (1.0 - (l1 * l1 + l2 * l2 + i3 - 3.0) / J)


def planar_reference(p, volt, t_eval, kinks):
    """Displacement (m) of the planar DEA. ``p``: dict with L1 L2 H lam1p lam2p eps mu0 J0
    mu J tau (lists). ``volt(t)`` in V."""
    mu, J, tau = (np.asarray(p[k], float) for k in ("mu", "J", "tau"))
    n = len(mu)
    l2 = p["lam2p"]
    P1 = p["mu0"] * p["L2"] * p["H"] * (p["lam1p"] - p["lam1p"] ** -3 * l2 ** -2) / (
        1.0 - (p["lam1p"] ** 2 + l2 ** 2 + p["lam1p"] ** -2 * l2 ** -2 - 3.0) / p["J0"])  # eq 11

    def force(phi, lam, x1, x2):  # eq 12 with eq 5
        s = gent(lam, l2, p["mu0"], p["J0"]) + np.sum(gent(lam / x1, l2 / x2, mu, J))
        return p["L2"] * p["H"] / lam * (s - p["eps"] * (phi * lam * l2 / p["H"]) ** 2)

    def lam_of(phi, x1, x2):
        return brentq(lambda lam: force(phi, lam, x1, x2) - P1, 1.0001, 4.0, xtol=1e-15,
                      rtol=1e-15)

    def rhs(t, x):
        x1, x2 = x[:n], x[n:]
        lam = lam_of(volt(t), x1, x2)
        e1, e2 = lam / x1, l2 / x2
        s1, s2 = gent(e1, e2, mu, J), gent(e2, e1, mu, J)
        eta = mu * tau  # eq 9
        return np.concatenate([x1 * (s1 - s2 / 2) / (3 * eta),  # eq 7
                               x2 * (s2 - s1 / 2) / (3 * eta)])  # eq 8

    x0 = np.concatenate([np.full(n, p["lam1p"]), np.full(n, l2)])
    xs = piecewise_solve(rhs, x0, t_eval, kinks)
    lam = np.array([lam_of(volt(t), x[:n], x[n:]) for t, x in zip(t_eval, xs)])
    return (lam - p["lam1p"]) * p["L1"]


# --- paper 002: mass cone with membrane inertia (rebuilt eq 24 + eq 22) ---------------------
def huang_reference(p, volt, t_eval, kinks):
    """Displacement z2 (m). ``p``: R R0 d0 eps rho z1 P mu0 J0 mu J tau (lists)."""
    mu, J, T = (np.asarray(p[k], float) for k in ("mu", "J", "tau"))
    eta = mu * T  # eq 23
    n = len(mu)
    R, R0, d0 = p["R"], p["R0"], p["d0"]
    L0 = R - R0
    kI = p["rho"] * (R + 3 * R0) / (6 * (R + R0))
    lam_pre = math.sqrt(p["z1"] ** 2 + L0 ** 2) / L0

    def rhs(t, y):  # y[1] = TAU_V * dlam/dt (scaled so Radau does not chase the
        # ~540 Hz membrane mode with its v-error: as the package's error norm)
        lam, v, x1, x2 = y[0], y[1] / TAU_V, y[2:2 + n], y[2 + n:]
        phi = volt(t)
        den0 = 1 - (lam ** 2 + lam ** -2 - 2) / p["J0"]
        deni = 1 - (lam ** 2 * x1 ** -2 + lam ** -2 * x2 ** -2 + x1 ** 2 * x2 ** 2 - 3) / J
        S = (p["mu0"] * (lam - lam ** -3) / den0
             + np.sum(mu * (lam * x1 ** -2 - lam ** -3 * x2 ** -2) / deni))
        a = lam ** 2 - 1
        lhs = kI * lam ** 2 * L0 ** 2 / a
        r = (kI * lam * L0 ** 2 / a ** 2 * v ** 2
             + p["P"] * lam / (math.pi * d0 * (R + R0) * math.sqrt(a))
             + p["eps"] * phi ** 2 * lam / d0 ** 2 - S)
        dx1 = -(mu / eta) * (-lam ** 2 * x1 ** -2 + x1 ** 2 * x2 ** 2) / deni
        dx2 = -(mu / eta) * (-lam ** -2 * x2 ** -2 + x1 ** 2 * x2 ** 2) / deni
        return np.concatenate([[v, TAU_V * r / lhs], dx1, dx2])

    y0 = np.concatenate([[lam_pre, 0.0], np.full(n, lam_pre), np.full(n, 1 / lam_pre)])
    ys = piecewise_solve(rhs, y0, t_eval, kinks)
    return L0 * np.sqrt(ys[:, 0] ** 2 - 1) - p["z1"]


def huang_equilibrium_load(p):
    L0 = p["R"] - p["R0"]
    lam = math.sqrt(p["z1"] ** 2 + L0 ** 2) / L0
    S = p["mu0"] * (lam - lam ** -3) / (1 - (lam ** 2 + lam ** -2 - 2) / p["J0"])
    return S * math.pi * p["d0"] * (p["R"] + p["R0"]) * math.sqrt(lam ** 2 - 1) / lam


# --- paper 001: Kelvin-chain cone ----------------------------------------------------------
def kelvin_reference(p, volt, t_eval, kinks):
    """Displacement (m). ``p``: R R0 d0 eps rho z1 P mu1 J1 mu J eta (lists)."""
    mu, J, eta = (np.asarray(p[k], float) for k in ("mu", "J", "eta"))
    n = len(mu)
    R, R0, d0 = p["R"], p["R0"], p["d0"]
    L0 = R - R0
    kI = p["rho"] * (R + 3 * R0) / (6 * (R + R0))
    lam_pre = math.sqrt(p["z1"] ** 2 + L0 ** 2) / L0

    def s(x, m, j):  # thesis eq 30/33 spring stress in the cone mode
        return m * (x ** 2 - x ** -2) / (1 - (x ** 2 + x ** -2 - 2) / j)

    def rhs(t, y):
        lam, v, xk = y[0], y[1] / TAU_V, y[2:]
        x1 = lam / np.prod(xk)
        sigma = s(x1, p["mu1"], p["J1"])
        a = lam ** 2 - 1
        r = (kI * lam * L0 ** 2 / a ** 2 * v ** 2
             + p["P"] * lam / (math.pi * d0 * (R + R0) * math.sqrt(a))
             + p["eps"] * volt(t) ** 2 * lam / d0 ** 2 - sigma / lam)
        return np.concatenate([[v, TAU_V * r / (kI * lam ** 2 * L0 ** 2 / a)],
                               (sigma - s(xk, mu, J)) / eta])

    y0 = np.concatenate([[lam_pre, 0.0], np.ones(n)])
    # LSODA: ~8x faster than Radau here (Kelvin elements with 1e-4 s time constants relaxing
    # from the thesis's x0); agrees with Radau at rtol 1e-9 to 3e-9
    ys = piecewise_solve(rhs, y0, t_eval, kinks, method="LSODA")
    return L0 * np.sqrt(ys[:, 0] ** 2 - 1) - p["z1"]
