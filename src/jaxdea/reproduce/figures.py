"""Paper 000's figures regenerated from power maps of the fitted set (matplotlib, the
papers' layout: one panel per configuration, mW and g on the axes).

Every figure takes ``maps``: ``{case: xarray.Dataset}`` with dims (M, c, f) from
:func:`jaxdea.powermap` (the case names of :data:`jaxdea.reproduce.peaks.CASES`).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from ..provenance import figure_metadata  # noqa: E402

__all__ = ["fig6", "fig7", "fig9", "fig10", "fig11", "tradeoff"]

SINGLE = ("SCDEA-LS", "DCDEA-RR", "DCDEA-LS-B", "DCDEA-LS-A")
DOUBLE = ("DCDEA-RR-anti", "DCDEA-LS-anti", "DCDEA-LS-in")
#: The single-actuation counterpart of each double case (Fig 10's ratio).
COUNTERPART = {"DCDEA-RR-anti": "DCDEA-RR", "DCDEA-LS-anti": "DCDEA-LS-A",
               "DCDEA-LS-in": "DCDEA-LS-A"}


def _edges(v):
    v = np.asarray(v, float)
    if v.size == 1:
        return np.array([v[0] * 0.9, v[0] * 1.1])
    if np.all(v > 0) and v[-1] / v[0] > 20:
        lv = np.log(v)
        mid = 0.5 * (lv[1:] + lv[:-1])
        return np.exp(np.concatenate([[2 * lv[0] - mid[0]], mid, [2 * lv[-1] - mid[-1]]]))
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


def _mesh(ax, x, y, z, label, fig, log=False, cmap="viridis"):
    z = np.ma.masked_invalid(np.asarray(z, float))
    norm = None
    if log and z.count() and z.min() > 0:
        norm = LogNorm(vmin=float(z.min()), vmax=float(z.max()))
    m = ax.pcolormesh(_edges(x), _edges(y), z, shading="flat", cmap=cmap, norm=norm)
    fig.colorbar(m, ax=ax, label=label)
    if np.asarray(x).size > 1 and np.asarray(x)[-1] / max(np.asarray(x)[0], 1e-30) > 20:
        ax.set_xscale("log")
    if np.asarray(y).size > 1 and np.asarray(y)[-1] / max(np.asarray(y)[0], 1e-30) > 20:
        ax.set_yscale("log")


def _save(fig, path):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, metadata=figure_metadata(path))
    plt.close(fig)
    return path


def _pmax(ds):
    return ds["P_out"].max("f", skipna=True)


def _sel(ds, **kw):
    return ds.sel(**kw, method="nearest")


def fig6(maps: dict, path, mass: float = 1e-4, damping: float = 0.1):
    """Fig 6: amplitude and P_out against f, M = 0.1 g and c = 0.1 N s/m (the four
    single-actuation cases)."""
    fig, axes = plt.subplots(2, 4, figsize=(15, 6), sharex=True)
    for j, case in enumerate(SINGLE):
        ds = _sel(maps[case], M=mass, c=damping)
        f = ds["f"].values
        axes[0, j].plot(f, ds["amplitude"].values * 1e3, "k-")
        axes[1, j].plot(f, ds["P_out"].values * 1e3, "r-")
        axes[0, j].set_title(case)
        axes[0, j].set_ylabel("amplitude (mm)")
        axes[1, j].set_ylabel("P_out (mW)")
        axes[1, j].set_xlabel("f (Hz)")
    fig.suptitle(f"Fig 6: M = {float(ds['M']) * 1e3:g} g, c = {float(ds['c']):g} N s/m")
    fig.tight_layout()
    return _save(fig, path)


def fig7(maps: dict, path):
    """Fig 7: P_max over M x c for the four single-actuation cases."""
    fig, axes = plt.subplots(1, 4, figsize=(17, 4))
    for ax, case in zip(axes, SINGLE):
        p = _pmax(maps[case])
        _mesh(ax, p["c"].values, p["M"].values * 1e3, p.values * 1e3, "P_max (mW)", fig,
              log=True)
        ax.set(title=case, xlabel="c (N s/m)", ylabel="M (g)")
    fig.suptitle("Fig 7: maximum power output against payload damping and mass")
    fig.tight_layout()
    return _save(fig, path)


def _f_c(maps, cases, path, title, mass):
    fig, axes = plt.subplots(2, len(cases), figsize=(5.2 * len(cases), 7.5))
    axes = np.asarray(axes).reshape(2, len(cases))
    for j, case in enumerate(cases):
        ds = _sel(maps[case], M=mass)
        f, c = ds["f"].values, ds["c"].values
        _mesh(axes[0, j], f, c, ds["P_out"].values * 1e3, "P_out (mW)", fig)
        _mesh(axes[1, j], f, c, ds["efficiency"].values * 100, "efficiency (%)", fig,
              cmap="magma")
        axes[0, j].set(title=case, ylabel="c (N s/m)")
        axes[1, j].set(xlabel="f (Hz)", ylabel="c (N s/m)")
    fig.suptitle(f"{title} (M = {float(ds['M']) * 1e3:g} g)")
    fig.tight_layout()
    return _save(fig, path)


def fig9(maps: dict, path, mass: float = 2e-3):
    """Fig 9: P_out and efficiency over f x c, M = 2 g, SCDEA-LS, DCDEA-RR, DCDEA-LS-A."""
    return _f_c(maps, ("SCDEA-LS", "DCDEA-RR", "DCDEA-LS-A"), path,
                "Fig 9: power output and efficiency, single actuation", mass)


def fig11(maps: dict, path, mass: float = 2e-3):
    """Fig 11: as Fig 9 for the three double-actuation cases."""
    return _f_c(maps, DOUBLE, path, "Fig 11: power output and efficiency, double actuation",
                mass)


def fig10(maps: dict, path):
    """Fig 10: P_max over M x c of the double cases (a-c) and their ratio to the
    single-actuation counterpart (d-f)."""
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    for j, case in enumerate(DOUBLE):
        p = _pmax(maps[case])
        ratio = p / _pmax(maps[COUNTERPART[case]])
        _mesh(axes[0, j], p["c"].values, p["M"].values * 1e3, p.values * 1e3, "P_max (mW)",
              fig, log=True)
        _mesh(axes[1, j], p["c"].values, p["M"].values * 1e3, ratio.values,
              f"P_max ratio to {COUNTERPART[case]}", fig, cmap="coolwarm")
        axes[0, j].set(title=case, xlabel="c (N s/m)", ylabel="M (g)")
        axes[1, j].set(xlabel="c (N s/m)", ylabel="M (g)")
    fig.suptitle("Fig 10: double actuation, and its ratio to single actuation")
    fig.tight_layout()
    return _save(fig, path)


def tradeoff(designs, fitted: dict, path):
    """The trade-off between the claims that conflict, over every design a calibration
    evaluated (``designs``: a record array with ``loss``, ``margin_1a``, ``margin_2a``,
    ``fig9_error``): finding 1a's and 2a's margins (positive: met) against the Fig 9 error,
    coloured by the loss; ``fitted``: the fitted set's three values (a red star)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    loss = np.asarray(designs["loss"], float)
    y = np.asarray(designs["fig9_error"], float)
    for ax, key, label in ((axes[0], "margin_1a", "finding 1a margin: log(P RR / P LS-B)"),
                           (axes[1], "margin_2a", "finding 2a margin: log(P RR-anti / "
                                                  "max P LS double)")):
        x = np.asarray(designs[key], float)
        ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(loss)
        sc = ax.scatter(x[ok], y[ok], c=np.log10(loss[ok]), s=9, cmap="viridis_r")
        ax.plot(fitted[key], fitted["fig9_error"], "r*", ms=16, label="fitted set")
        ax.axvline(0.0, color="k", lw=0.8)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set(xlabel=label + ", c = 0.1")
        ax.legend(loc="upper right")
    axes[0].set_ylabel("Fig 9 error (largest part, in tolerances)")
    axes[0].set_yscale("log")
    fig.colorbar(sc, ax=axes, label="log10 loss")
    fig.suptitle(f"Every design the calibration evaluated ({loss.size}); a claim is met right "
                 "of the solid line, Fig 9 below the dashed one")
    return _save(fig, path)
