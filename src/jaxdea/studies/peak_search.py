"""Where the P_max search puts its frequencies (host side of `design.peak_designs`).

Pure numpy on the samples of one design (frequencies, P, dP/df): where the hills of P(f)
are (:func:`hills`), where the next level's cells go (:func:`next_frequencies`), when a
bracket is narrow enough to fit (:func:`bracket_ready`), and P_max with its gradient where
the fit of dP/df is zero (:func:`stationary_point`). docs/models.md, section 10, gives the
method and why.
"""

from __future__ import annotations

import numpy as np


def _hermite_peak(f0, p0, g0, f1, p1, g1):
    """Maximum of the cubic Hermite interpolant of (P, dP/df) on [f0, f1]: (f, P)."""
    h = f1 - f0
    # p(s) = p0 + h g0 s + (3 (p1 - p0) - h (2 g0 + g1)) s^2 + (2 (p0 - p1) + h (g0 + g1)) s^3
    c1, c2, c3 = h * g0, 3 * (p1 - p0) - h * (2 * g0 + g1), 2 * (p0 - p1) + h * (g0 + g1)
    roots = np.roots([3 * c3, 2 * c2, c1]) if abs(c3) + abs(c2) > 0 else np.array([])
    s = np.concatenate([[0.0, 1.0], roots[np.isreal(roots)].real])
    s = s[(s >= 0) & (s <= 1)]
    p = p0 + c1 * s + c2 * s**2 + c3 * s**3
    i = int(np.argmax(p))
    return f0 + s[i] * h, p[i]


def hills(f, p, g, band) -> list[tuple[float, int, float]]:
    """The intervals between neighbouring samples that hold a local maximum of P(f).

    **Arguments:**

    - `f`, `p`, `g`: samples of f (Hz), P (NaN or -inf where not converged) and dP/df of
      one design, in any order.
    - `band`: ``(f_lo, f_hi)``.

    **Returns:**

    ``[(score, a, f_c), ...]``, best first, for the intervals ``[f[a], f[a + 1]]`` of the
    samples *sorted by f* (so ``a`` indexes the sorted samples) where dP/df changes sign
    from + to -, where the cubic Hermite interpolant of (P, dP/df) peaks inside, or, at a
    band edge, where P falls away from the edge; ``f_c`` is the interpolant's maximum and
    ``score`` the larger of its value and the interval's end samples. A resonance narrower
    than the sample spacing is found by its slopes: left of it dP/df > 0, right of it < 0,
    however low P is at both samples.
    """
    f, p, g = _sorted(f, p, g)
    lo, hi = band
    out = []
    for a in range(len(f) - 1):
        if not (np.isfinite(p[a]) and np.isfinite(p[a + 1]) and f[a + 1] > f[a]):
            continue
        fc, pc = _hermite_peak(f[a], p[a], g[a], f[a + 1], p[a + 1], g[a + 1])
        turn = g[a] > 0 >= g[a + 1]
        inside = f[a] < fc < f[a + 1]
        edge = (a == 0 and f[a] <= lo and g[a] < 0) or (
            a == len(f) - 2 and f[a + 1] >= hi and g[a + 1] > 0)
        if turn or inside or edge:
            out.append((float(max(pc, p[a], p[a + 1])), a, float(fc)))
    if not out and np.isfinite(p).any():  # no slope information: the best sample's sides
        j = int(np.nanargmax(np.where(np.isfinite(p), p, np.nan)))
        for a in (j - 1, j):
            if 0 <= a < len(f) - 1 and f[a + 1] > f[a]:
                out.append((float(p[j]), a, float(f[j])))
    return sorted(out, key=lambda h: -h[0])


def _sorted(f, p, g):
    order = np.argsort(f)
    return (np.asarray(f, float)[order], np.asarray(p, float)[order],
            np.nan_to_num(np.asarray(g, float)[order]))


def bracket_ready(f, p, g, band) -> bool:
    """Whether the best :func:`hills` interval is narrow enough for the final level: at a
    band edge, or at most half the peak's curvature length ``sqrt(P / |d2P/df2|)`` (with
    d2P/df2 from the slopes at its ends), so that low-order fits over it are exact to
    ~1e-6 of the peak."""
    found = hills(f, p, g, band)
    if not found:
        return True
    _, a, fc = found[0]
    fs, ps, gs = _sorted(f, p, g)
    lo, hi = band
    if fc <= lo or fc >= hi:
        return True
    width = fs[a + 1] - fs[a]
    curv = (gs[a + 1] - gs[a]) / width
    if not (gs[a] > 0 >= gs[a + 1]) or curv >= 0:
        return False
    return bool(width <= 0.5 * np.sqrt(max(ps[a], ps[a + 1], 0.0) / -curv))


def next_frequencies(f, p, g, level: int, grid: int, band, final: bool = False) -> np.ndarray:
    """The ``grid`` frequencies of refinement ``level`` (>= 1) of one design.

    A bracketing level shares the cells between the best ``grid // 2**level`` :func:`hills`
    (at least one; best first), with points evenly inside each interval, which shrinks the
    bracket of a maximum by the number of points + 1. The ``final`` level spreads the cells
    evenly over the best hill's interval, ends included, for the fits of
    :func:`stationary_point`.

    **Arguments:**

    - `f`, `p`, `g`: every sample of the design so far (see :func:`hills`).
    - `level`: this level (1, 2, ...).
    - `grid`: cells per level.
    - `band`: ``(f_lo, f_hi)``.
    - `final`: the last level.

    **Returns:**

    ``(grid,)`` frequencies in the band.
    """
    lo, hi = band
    fs = np.sort(np.asarray(f, float))
    found = hills(f, p, g, band)
    if not found:  # nothing converged: sample the band again (the caller reports status)
        return np.linspace(lo, hi, grid)
    if final:
        _, a, _ = found[0]
        return np.linspace(fs[a], fs[a + 1], grid)
    found = found[:max(1, grid // 2**level)]
    counts = np.full(len(found), grid // len(found))
    counts[:grid % len(found)] += 1
    return np.concatenate([np.linspace(fs[a], fs[a + 1], m + 2)[1:-1]
                           for (_, a, _), m in zip(found, counts)])


def stationary_point(f, p, g, rows):
    """Where dP/df = 0 among the final level's cells of one design, and the values there.

    Fits a quintic (fewer coefficients with fewer cells) to dP/df over the cells and takes
    its root inside them nearest the best cell; every row of ``rows`` (P, the metrics,
    the gradient) is interpolated there by the same fit. This is the refinement "solve
    dP/df = 0" of the envelope theorem: the gradient of P_max is dP/dtheta at that
    root, and a cell a little off the root would add ``dP/df df*/dtheta`` to the
    derivative of the reported P_max, large for a narrow resonance that moves with the
    design. Where there is no root inside (a maximum at a band edge) or a cell did not
    converge, the best cell is returned as it is.

    **Arguments:**

    - `f`, `p`, `g`: the cells' frequencies, P (-inf where not converged), dP/df.
    - `rows`: ``(cells, m)`` values to give at the stationary point.

    **Returns:**

    ``(f*, rows at f*)``.
    """
    f, p, g = (np.asarray(a, float) for a in (f, p, g))
    rows = np.asarray(rows, float)
    j = int(np.argmax(p))
    deg = min(5, len(f) - 1)
    if not (np.isfinite(p).all() and np.isfinite(g).all() and np.isfinite(rows).all()) \
            or np.ptp(f) <= 0 or deg < 1:
        return f[j], rows[j]
    fit = np.polynomial.Polynomial.fit(f, g, deg)
    roots = fit.roots()
    roots = roots[np.isreal(roots)].real
    roots = roots[(roots >= f.min()) & (roots <= f.max())]
    if roots.size == 0:
        return f[j], rows[j]
    fstar = roots[np.argmin(np.abs(roots - f[j]))]
    slope = fit.deriv()
    for _ in range(3):  # Newton polish (the companion-matrix roots are good to ~1e-8)
        if slope(fstar) != 0:
            fstar = fstar - fit(fstar) / slope(fstar)
    if slope(fstar) >= 0:  # a minimum of P, not a peak
        return f[j], rows[j]
    out = np.array([np.polynomial.Polynomial.fit(f, col, deg)(fstar) for col in rows.T])
    return fstar, out
