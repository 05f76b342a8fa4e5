"""Fig-12 grid of the rotational double cone (paper 003): jaxdea vs scipy, same run.

jaxdea: the whole (r_i, d) grid as ONE vmapped, jitted call of :func:`jaxdea.rotary_study`
(Newton with voltage continuation + stiffness-eigenvalue stability check per point).
Baseline: an independent numpy transcription of eqs 7-10, 16-24, 28, 30 (Table 1), solved point
by point with ``scipy.optimize.root`` (hybr, finite-difference Jacobian) from the unactuated
state ``q = 0``. Both solve the same points; the angles are compared.

Usage: ``python bench/rotary_bench.py [--ri 2e-3:7e-3:26] [--d 4e-3:18e-3:57] [--repeat 5]``.
Ends with one line ``RESULT grid_points=... jaxdea_s=... scipy_s=... ratio=...``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.optimize import root

# ---- independent numpy transcription (paper 003, Table 1, no gravity) ----------------------
R_O, H, F = 22.5e-3, 2e-3, 0.0
Z0 = 50e-6
ALPHA = np.array([2.0, 4.0])
BETA = np.array([1.707e6, -0.023e6])
GAMMA = np.array([1.298e6, -0.955e6])
EPS = 8.854187817e-12 * 2.8
E_MAX = 80e6
PATTERN = np.array([0.0, 1.0, 1.0, 0.0])  # B + C
SX = np.array([-1.0, 1.0, -1.0, 1.0])  # sign of r_i in A, B, C, D
SY = np.array([1.0, 1.0, -1.0, -1.0])  # sign of d + f
K1X = np.array([-R_O, R_O, -R_O, R_O])
K1Y = np.array([H, H, -H, -H])


def np_torque(q, ri, d, e_active):
    """Generalized static forces tau(q) = -J^T f (eqs 16-28) with the frozen eq-9 field."""
    gx, gy, th = q
    c, s = np.cos(th), np.sin(th)
    px, py = ri * SX, (d + F) * SY
    k2x = gx + c * px - s * py
    k2y = gy + s * px + c * py
    dx, dy = k2x - K1X, k2y - K1Y
    ell = np.hypot(dx, dy)
    span = R_O - ri
    lam = ell / span
    sig = (BETA[None, :] * lam[:, None] ** ALPHA - GAMMA[None, :] * lam[:, None] ** -ALPHA).sum(1)
    sig = sig - EPS * e_active ** 2
    force = sig * np.pi * Z0 * (R_O + ri) / (2.0 * lam)
    # dl/dq rows: (dx, dy, dx * dk2x/dth + dy * dk2y/dth) / l
    dk2x = -s * px - c * py
    dk2y = c * px - s * py
    jac = np.stack([dx / ell, dy / ell, (dx * dk2x + dy * dk2y) / ell], axis=1)
    return -jac.T @ force


def scipy_angle(ri, d):
    if not (0 < ri < R_O and d + F > H):
        return np.nan
    e_active = PATTERN * E_MAX  # frozen field: eq-30 voltage gives E_max at q = 0
    sol = root(np_torque, np.zeros(3), args=(ri, d, e_active), method="hybr", tol=1e-10)
    return np.degrees(sol.x[2]) if sol.success else np.nan


def main(argv=None) -> int:
    from jaxdea.cli.args import parse_points

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ri", default="2e-3:7e-3:26")
    p.add_argument("--d", default="4e-3:18e-3:57")
    p.add_argument("--repeat", type=int, default=5, help="timed jaxdea calls (best is kept)")
    args = p.parse_args(argv)
    ri = parse_points(args.ri + ":lin" if args.ri.count(":") == 2 else args.ri, "--ri")
    d = parse_points(args.d + ":lin" if args.d.count(":") == 2 else args.d, "--d")
    n = ri.size * d.size

    import jaxdea

    model = jaxdea.load_config(Path(__file__).parents[1] / "configs" / "rotary_dcdea.toml")
    t0 = time.perf_counter()
    ds = jaxdea.rotary_study(model, ri, d)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        ds = jaxdea.rotary_study(model, ri, d)
        times.append(time.perf_counter() - t0)
    jax_s = min(times)
    print(f"jaxdea: {n} points in {jax_s:.4f} s (first call incl. compile {compile_s:.2f} s), "
          f"{int((ds['status'] != 0).sum())} non-ok")

    t0 = time.perf_counter()
    ref = np.array([[scipy_angle(r, dd) for dd in d] for r in ri])
    scipy_s = time.perf_counter() - t0
    diff = np.nanmax(np.abs(ref - ds["theta_deg"].values))
    print(f"scipy root one by one: {scipy_s:.3f} s; max |theta difference| {diff:.2e} deg; "
          f"{int(np.isnan(ref).sum())} scipy failures")
    th = ds["theta_deg"].values
    i, j = np.unravel_index(np.nanargmax(th), th.shape)
    print(f"grid optimum {th[i, j]:.3f} deg at r_i = {1e3 * ri[i]:.3f} mm, d = {1e3 * d[j]:.3f} mm")
    print(f"RESULT grid_points={n} jaxdea_s={jax_s:.5f} scipy_s={scipy_s:.4f} "
          f"ratio={scipy_s / jax_s:.1f} compile_s={compile_s:.2f} max_abs_diff_deg={diff:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
