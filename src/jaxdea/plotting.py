"""Matplotlib figures of jaxdea results (SI data, plotted in mm / mW / g)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: figures go to files
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from .calibration import CalibrationResult, Data, FrequencyResponse  # noqa: E402
from .payloads import PARAMETER_UNITS  # noqa: E402
from .provenance import figure_metadata  # noqa: E402
from .studies.optimise import OptimiseResult  # noqa: E402


def plot_sweep(ds: xr.Dataset, path: str | Path | None = None):
    """Amplitude and P_out against frequency, in the style of paper 000 Fig 6.

    Cells with a non-zero ``status`` are shown as red crosses on the f axis.
    """
    f = ds["f"].values
    ok = ds["status"].values == 0
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(6.4, 5.6))
    ax1.plot(f[ok], 1e3 * ds["amplitude"].values[ok], "k-")
    ax1.set_ylabel("amplitude (mm)")
    ax2.plot(f[ok], 1e3 * ds["P_out"].values[ok], "b-")
    ax2.set_ylabel(r"$P_{out}$ (mW)")
    ax2.set_xlabel("frequency (Hz)")
    if (~ok).any():
        for ax in (ax1, ax2):
            ax.plot(f[~ok], np.zeros((~ok).sum()), "rx", label="failed cell (status != 0)")
        ax1.legend(loc="best", fontsize=8)
    if ok.any():
        i = int(np.nanargmax(np.where(ok, ds["P_out"].values, -np.inf)))
        ax2.annotate(f"{1e3 * ds['P_out'].values[i]:.2f} mW at {f[i]:.1f} Hz",
                     (f[i], 1e3 * ds["P_out"].values[i]), textcoords="offset points",
                     xytext=(8, -12), fontsize=8)
    a = ds.attrs
    title = (f"{a.get('model', '')} drive {a.get('drive', '')}"
             + (f" (phase {a['phase']:.2f} rad)" if a.get("drive") == "both" else "")
             + f", M = {1e3 * a.get('mass', np.nan):g} g, c = {a.get('damping', np.nan):g} N s/m")
    ax1.set_title(title, fontsize=10)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    return _save(fig, path)


# ---- power maps (paper 000 Figs 7, 9, 10) ---------------------------------------------------


def _edges(v: np.ndarray, log: bool) -> np.ndarray:
    """Cell edges around the centres ``v`` (geometric midpoints on a log axis)."""
    v = np.asarray(v, dtype=float)
    if v.size == 1:
        return v * np.array([0.9, 1.1]) if log else v + np.array([-0.5, 0.5])
    w = np.log(v) if log else v
    mid = 0.5 * (w[1:] + w[:-1])
    e = np.concatenate([[2 * w[0] - mid[0]], mid, [2 * w[-1] - mid[-1]]])
    return np.exp(e) if log else e


def _is_log(v: np.ndarray) -> bool:
    return bool(np.all(np.asarray(v) > 0) and np.asarray(v).size > 1)


def _over_phase(da: xr.DataArray) -> tuple[xr.DataArray, str]:
    """Max over the phase axis, if the map has one (with a note for the title)."""
    if "phase" in da.dims:
        return da.max("phase", skipna=True), ", max over phase"
    return da, ""


def _map_title(ds: xr.Dataset) -> str:
    a = ds.attrs
    return (f"{a.get('model', '')} drive {a.get('drive', '')}, {a.get('protocol', 'paper')} "
            f"protocol ({a.get('cycles', '?')} cycles)")


def _mc_mesh(ax, x, y, z, label, fig, *, norm=None, cmap="viridis", contours=True):
    """pcolormesh of z[y, x] with log axes where possible, contour lines and a colorbar."""
    xlog, ylog = _is_log(x), _is_log(y)
    mesh = ax.pcolormesh(_edges(x, xlog), _edges(y, ylog), np.ma.masked_invalid(z),
                         cmap=cmap, norm=norm, shading="flat")
    if contours and min(z.shape) >= 2 and np.isfinite(z).sum() >= 4:
        try:
            cs = ax.contour(x, y, np.ma.masked_invalid(z), colors="k", linewidths=0.6,
                            norm=norm, levels=8 if norm is None else None)
            ax.clabel(cs, fontsize=7, fmt="%.3g")
        except (ValueError, TypeError):  # degenerate field (e.g. constant): no contour
            pass
    ax.set_xscale("log" if xlog else "linear")
    ax.set_yscale("log" if ylog else "linear")
    fig.colorbar(mesh, ax=ax, label=label)
    return mesh


def _save(fig, path, dpi: int = 130):
    fig.tight_layout()
    if path is not None:  # a PNG carries jaxdea's mark (jaxdea.provenance)
        fig.savefig(path, dpi=dpi, metadata=figure_metadata(path))
        plt.close(fig)
    return fig


def law_dim(ds: xr.Dataset) -> str:
    """The map's payload axis besides M: ``"c"`` (linear dashpot) or a law parameter."""
    return next(str(d) for d in ds["P_out"].dims if d not in ("M", "f", "phase"))


def _law_label(ds: xr.Dataset, k: str) -> str:
    unit, name = PARAMETER_UNITS.get(k, ("", k))
    return f"{name} ({unit})" if unit else name


def plot_pmax(ds: xr.Dataset, path: str | Path | None = None):
    """P_max (mW) over payload mass M (g) x damping c (N s/m) (or the map's payload-law
    axis), as paper 000 Fig 7.

    Blank cells: no frequency of that payload finished with status 0. The largest P_max is
    marked with a star.
    """
    k = law_dim(ds)
    pmax, note = _over_phase(ds["P_max"])
    z = 1e3 * pmax.transpose(k, "M").values
    m_g, c = 1e3 * ds["M"].values, ds[k].values
    fig, ax = plt.subplots(figsize=(6.4, 5.0))
    _mc_mesh(ax, m_g, c, z, r"$P_{max}$ (mW)", fig)
    if np.isfinite(z).any():
        j, i = np.unravel_index(np.nanargmax(z), z.shape)
        ax.plot(m_g[i], c[j], "w*", ms=12, mec="k",
                label=f"{np.nanmax(z):.2f} mW at M = {m_g[i]:.3g} g, {k} = {c[j]:.3g} "
                      f"{PARAMETER_UNITS.get(k, ('',))[0]}")
        ax.legend(loc="upper left", fontsize=7)
    ax.set_xlabel("payload mass M (g)")
    ax.set_ylabel(_law_label(ds, k))
    ax.set_title(f"{_map_title(ds)}{note}", fontsize=9)
    return _save(fig, path)


def plot_pout_fc(ds: xr.Dataset, path: str | Path | None = None, mass: float | None = None):
    """P_out (mW) over frequency f x damping c (or the payload-law axis) at the M nearest
    ``mass`` (kg), as Fig 9.

    ``mass=None``: the M of the largest P_max. Cells with status != 0 are blank; white dots
    mark f_at_P_max for each c.
    """
    k = law_dim(ds)
    if mass is None:
        pm, _ = _over_phase(ds["P_max"])
        vals = np.nan_to_num(pm.transpose("M", k).values, nan=-np.inf)
        i = int(np.unravel_index(np.argmax(vals), vals.shape)[0])
    else:
        if not np.isfinite(mass):
            raise ValueError(f"--mass must be finite, got {mass!r}")
        i = int(np.argmin(np.abs(ds["M"].values - mass)))
    sel = ds.isel(M=i)
    pout, note = _over_phase(sel["P_out"].where(sel["status"] == 0))
    z = 1e3 * pout.transpose(k, "f").values
    f, c = ds["f"].values, ds[k].values
    fig, ax = plt.subplots(figsize=(6.4, 5.0))
    _mc_mesh(ax, f, c, z, r"$P_{out}$ (mW)", fig, contours=True)
    ax.set_xscale("linear")
    if "phase" not in sel["f_at_P_max"].dims:
        ax.plot(sel["f_at_P_max"].values, c, "w.", ms=5, label=r"$f$ at $P_{max}$")
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("frequency f (Hz)")
    ax.set_ylabel(_law_label(ds, k))
    ax.set_title(f"{_map_title(ds)}, M = {1e3 * float(ds['M'][i]):.3g} g{note}", fontsize=9)
    return _save(fig, path)


def plot_pmax_ratio(ds: xr.Dataset, other: xr.Dataset, path: str | Path | None = None):
    """Ratio of two maps' P_max over M x c (``ds`` / ``other``), as paper 000 Fig 10.

    The maps must share their M and c axes. The colour scale is logarithmic and centred on
    1 (the contour ``ratio = 1`` is drawn in black).
    """
    law = law_dim(ds)
    if law_dim(other) != law:
        raise ValueError(f"--other: the maps have different payload axes ({law}, "
                         f"{law_dim(other)}); a ratio needs the same payload grid")
    for k in ("M", law):
        if ds[k].size != other[k].size or not np.allclose(ds[k].values, other[k].values,
                                                          rtol=1e-9, atol=0):
            raise ValueError(f"--other: the maps have different {k} axes; a ratio needs the "
                             "same payload grid")
    a, note = _over_phase(ds["P_max"])
    b, _ = _over_phase(other["P_max"])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (a / b.assign_coords(M=a["M"], **{law: a[law]})).transpose(law, "M").values
    r = np.where(np.isfinite(r) & (r > 0), r, np.nan)
    m_g, c = 1e3 * ds["M"].values, ds[law].values
    fig, ax = plt.subplots(figsize=(6.4, 5.0))
    norm = None
    if np.isfinite(r).any():
        span = max(float(np.nanmax(np.abs(np.log10(r)))), 1e-3)
        norm = matplotlib.colors.LogNorm(10 ** -span, 10 ** span)
    _mc_mesh(ax, m_g, c, r, r"$P_{max}$ ratio", fig, norm=norm, cmap="RdBu_r", contours=False)
    if min(r.shape) >= 2 and np.nanmin(r) < 1 < np.nanmax(r):
        ax.contour(m_g, c, np.ma.masked_invalid(r), levels=[1.0], colors="k", linewidths=1.0)
    ax.set_xlabel("payload mass M (g)")
    ax.set_ylabel(_law_label(ds, law))
    da, db = ds.attrs.get("drive", "?"), other.attrs.get("drive", "?")
    ax.set_title(f"P_max ratio: drive {da} / drive {db} ({ds.attrs.get('model', '')}){note}",
                 fontsize=9)
    return _save(fig, path)


# ---- rotational double cone (paper 003 Fig 12) ----------------------------------------------


def plot_rotary_study(ds: xr.Dataset, path: str | Path | None = None):
    """Steady rotation angle over inner radius x half spacer length (paper 003 Fig 12 style):
    filled contours with labelled iso-angle lines, the grid optimum marked, cells with a
    non-zero ``status`` (no stable equilibrium, not converged, invalid geometry) as red x."""
    ri = 1e3 * ds["ri"].values
    d = 1e3 * ds["d"].values
    th = ds["theta_deg"].values  # dims (ri, d)
    ok = ds["status"].values == 0
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    if ri.size > 1 and d.size > 1 and ok.any():
        z = np.where(ok, th, np.nan).T
        cf = ax.contourf(ri, d, z, levels=14, cmap="viridis")
        cs = ax.contour(ri, d, z, levels=cf.levels[::2], colors="k", linewidths=0.6)
        ax.clabel(cs, fmt="%.1f", fontsize=7)
        fig.colorbar(cf, ax=ax, label=r"rotation angle $\theta$ (deg)")
        i, j = np.unravel_index(int(np.nanargmax(np.where(ok, th, -np.inf))), th.shape)
        ax.plot(ri[i], d[j], "w*", ms=12, mec="k",
                label=f"max {th[i, j]:.2f} deg at r_i = {ri[i]:.2f} mm, d = {d[j]:.2f} mm")
        ax.legend(loc="upper right", fontsize=7)
    if (~ok).any():
        R, D = np.meshgrid(ri, d, indexing="ij")
        ax.plot(R[~ok], D[~ok], "rx", ms=4, label="status != 0")
    ax.set_xlabel(r"inner radius $r_i$ (mm)")
    ax.set_ylabel(r"half spacer length $d$ (mm)")
    a = ds.attrs
    ax.set_title(f"rotary DC-DEA steady angle ({a.get('field_mode', '')} field, "
                 f"g = {a.get('gravity', 0.0):g} m/s$^2$)", fontsize=10)
    return _save(fig, path)


def plot_transient(ds: xr.Dataset, path: str | Path | None = None):
    """Displacement vs time and vs voltage (hysteresis loops), as the papers' figures."""
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    t = ds["t"].values
    ax[0].plot(t, ds["voltage"].values / 1e3)
    ax[0].set(xlabel="t (s)", ylabel="voltage (kV)")
    ax[1].plot(t, ds["displacement"].values * 1e3)
    ax[1].set(xlabel="t (s)", ylabel="displacement (mm)")
    ax[2].plot(ds["voltage"].values / 1e3, ds["displacement"].values * 1e3, lw=0.8)
    ax[2].set(xlabel="voltage (kV)", ylabel="displacement (mm)")
    fig.suptitle(ds.attrs.get("model", ""))
    return _save(fig, path)


# ---- calibration ------------------------------------------------------------------------


_PLOT_UNITS = {"amplitude": (1e3, "mm"), "P_out": (1e3, "mW"), "displacement": (1e3, "mm"),
               "force": (1.0, "N")}


def plot_fit(result: CalibrationResult, data: Data, path=None):
    """Measured (markers) against the fitted model (lines) for every channel, with the
    residuals underneath; one colour per payload for frequency responses.

    **Arguments:**

    - `result`: what :func:`jaxdea.calibrate` returned.
    - `data`: the data it was fitted to.
    - `path`: if given, the figure is saved there (PNG) and closed.

    **Returns:**

    The matplotlib figure.
    """
    chans = list(result.prediction)
    fig, axes = plt.subplots(2, len(chans), figsize=(5.2 * len(chans), 5.6), squeeze=False,
                             sharex="col", gridspec_kw={"height_ratios": [3, 1]})
    for j, ch in enumerate(chans):
        k, unit = _PLOT_UNITS.get(ch, (1.0, ""))
        y, p = np.asarray(data.channels[ch]), np.asarray(result.prediction[ch]).ravel()
        ax, axr = axes[0, j], axes[1, j]
        if isinstance(data, FrequencyResponse):
            for gi, ((m, c), idx) in enumerate(data.groups().items()):
                col = f"C{gi}"
                ax.plot(data.f[idx], k * y[idx], "o", ms=4, color=col,
                        label=f"data M = {1e3 * m:g} g, c = {c:g} N s/m")
                ax.plot(data.f[idx], k * p[idx], "-", color=col)
                axr.plot(data.f[idx], k * (y[idx] - p[idx]), ".", color=col)
            axr.set_xlabel("frequency (Hz)")
        else:
            ax.plot(data.t, k * y, ".", ms=2, color="0.4", label="data")
            ax.plot(data.t, k * p, "-", color="C3", lw=1, label="model")
            axr.plot(data.t, k * (y - p), "-", color="C0", lw=0.7)
            axr.set_xlabel("time (s)")
        e_rms, e_m = result.metrics[ch]
        ax.set_title(f"{ch}: e_rms {e_rms:.2f} %, e_m {e_m:.2f} %", fontsize=10)
        ax.set_ylabel(f"{ch} ({unit})")
        axr.set_ylabel(f"data - model ({unit})")
        ax.legend(fontsize=7)
        for a in (ax, axr):
            a.grid(alpha=0.3)
    fig.suptitle(f"calibration ({result.method}): loss {result.loss:.3g}", fontsize=10)
    return _save(fig, path, dpi=120)


#: How each objective of :func:`jaxdea.optimise` is plotted: (scale, unit, axis label).
_OBJECTIVE_AXES = {"pmax": (1e3, "mW", r"$P_{max}$ over the band (mW)"),
                   "power": (1e3, "mW", r"$P_{out}$ (mW)"),
                   "efficiency": (1e2, "%", "efficiency (%)")}


def plot_optimise(result: OptimiseResult, path=None, objective: str = "pmax"):
    """The objective of every start against the iteration of :func:`jaxdea.optimise`, the
    start it returned highlighted; an infeasible start (failed orbit) leaves a gap.

    **Arguments:**

    - `result`: what :func:`jaxdea.optimise` returned.
    - `path`: if given, the figure is saved there (PNG) and closed.
    - `objective`: the objective it maximised, ``"pmax"``, ``"power"`` (both in mW) or
      ``"efficiency"`` (in %).

    **Returns:**

    The matplotlib figure.
    """
    k, unit, label = _OBJECTIVE_AXES[objective]
    hist = np.asarray(result.history, dtype=float)  # (iterations + 1, starts)
    y = k * np.where(np.isfinite(hist), hist, np.nan)
    it = np.arange(hist.shape[0])
    # the start it returned: the last objective nearest result.objective (which optimise may
    # recompute from rest, so it can differ from the history in the last digits)
    gap = np.abs(np.where(np.isfinite(hist[-1]), hist[-1], np.inf) - result.objective)
    best = np.flatnonzero(gap == gap.min())[:1] if np.isfinite(gap).any() else np.array([], int)
    others = [s for s in range(hist.shape[1]) if s not in best]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, s in enumerate(others):
        ax.plot(it, y[:, s], "o-", color="0.6", ms=3, lw=1,
                label="other starts" if i == 0 else None)
    for s in best:
        ax.plot(it, y[:, s], "o-", color="C3", ms=4, lw=2, label=f"start {s} (returned)")
    ax.set_xlabel("iteration")
    ax.set_ylabel(label)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_title(f"{objective}: {k * result.objective:.4g} {unit} (start 0: "
                 f"{k * result.start_objective:.4g} {unit})", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _save(fig, path)
