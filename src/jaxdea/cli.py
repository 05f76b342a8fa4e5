"""``jaxdea`` command line: ``jaxdea sweep CONFIG ...`` (see ``jaxdea sweep --help``)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np


def parse_range(text: str, name: str = "--freq") -> np.ndarray:
    """``MIN:MAX:STEP`` -> inclusive arithmetic range (``MAX`` included when on the grid)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{name} must be MIN:MAX:STEP, got {text!r}")
    try:
        lo, hi, step = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"{name} must be three numbers MIN:MAX:STEP, got {text!r}") from None
    if not all(math.isfinite(v) for v in (lo, hi, step)):
        raise ValueError(f"{name} values must be finite, got {text!r}")
    if step <= 0:
        raise ValueError(f"{name} STEP must be > 0, got {step:g}")
    if hi < lo:
        raise ValueError(f"{name} is empty: MAX = {hi:g} < MIN = {lo:g}")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    return np.round(lo + step * np.arange(n), 12)


def write_dataset(ds, out: Path) -> None:
    """Write NetCDF atomically (a temp file renamed into place), so an interrupted run never
    leaves a truncated file under the final name."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    ds.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, out)


def _sweep(args) -> int:
    import jaxdea
    from jaxdea.plotting import plot_sweep

    out = Path(args.out)
    if out.suffix != ".nc":
        raise ValueError(f"--out must end in .nc (NetCDF), got {out}")
    freq = parse_range(args.freq)
    model = jaxdea.load_config(args.config)
    control = jaxdea.StepControl(rtol=args.rtol)
    print(f"jaxdea sweep: {model.name}, drive {args.drive}, {freq.size} frequencies "
          f"{freq[0]:g}-{freq[-1]:g} Hz, {args.cycles} cycles (average last {args.average})",
          flush=True)
    ds = jaxdea.sweep(model, mass=args.mass, damping=args.damping, freq=freq, drive=args.drive,
                      phase=args.phase, cycles=args.cycles, average=args.average,
                      control=control)
    write_dataset(ds, out)
    i = int(np.argmax(ds["P_out"].values))
    bad = int((ds["status"] != 0).sum())
    print(f"wrote {out}: P_out max {1e3 * float(ds['P_out'][i]):.3f} mW at "
          f"{float(ds['f'][i]):g} Hz; {bad} failed cell(s)")
    if args.plot:
        plot_sweep(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxdea", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("sweep", help="frequency sweep of one payload (paper 000 protocol)")
    s.add_argument("config", help="TOML config, e.g. configs/dcdea_ls.toml")
    s.add_argument("--mass", type=float, required=True, help="payload mass M, kg")
    s.add_argument("--damping", type=float, required=True, help="payload damping c, N s/m")
    s.add_argument("--freq", required=True, help="FMIN:FMAX:DF in Hz (inclusive)")
    s.add_argument("--drive", default="A", choices=["A", "B", "both"])
    s.add_argument("--phase", type=float, default=0.0, help="phase of B vs A, rad [0, 2 pi)")
    s.add_argument("--cycles", type=int, default=100, help="drive periods per frequency")
    s.add_argument("--average", type=int, default=5, help="last periods averaged")
    s.add_argument("--rtol", type=float, default=1e-6, help="solver relative tolerance")
    s.add_argument("--out", required=True, help="output NetCDF file (.nc)")
    s.add_argument("--plot", help="optional PNG: amplitude and P_out against f (Fig 6 style)")
    s.set_defaults(func=_sweep)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxdea.config import ConfigError
    from jaxdea.sweep import SweepError

    try:
        return args.func(args)
    except (ConfigError, SweepError, ValueError) as exc:
        print(f"jaxdea: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
