"""Matplotlib figures of jaxdea results (SI data, plotted in mm / mW / g)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: figures go to files
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402


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
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=130)
        plt.close(fig)
    return fig
