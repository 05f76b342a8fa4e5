"""``jaxdea`` command line: ``jaxdea sweep|powermap|plot ...`` (see ``jaxdea COMMAND --help``)."""

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


def _min_max_count(parts: list[str], text: str, name: str) -> tuple[float, float, int]:
    """Finite ``MIN``, ``MAX`` and a count ``N >= 1`` from ``MIN:MAX:N`` pieces."""
    try:
        lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        raise ValueError(f"{name} must be MIN:MAX:N with N an integer, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} values must be finite, got {text!r}")
    if n < 1:
        raise ValueError(f"{name} is empty: N = {n} must be >= 1")
    return lo, hi, n


def parse_points(text: str, name: str) -> np.ndarray:
    """``MIN:MAX:N[:log|:lin]`` -> ``N`` points from MIN to MAX inclusive (default log)."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ValueError(f"{name} must be MIN:MAX:N[:log|:lin], got {text!r}")
    scale = parts[3] if len(parts) == 4 else "log"
    if scale not in ("log", "lin"):
        raise ValueError(f"{name} spacing must be log or lin, got {scale!r}")
    lo, hi, n = _min_max_count(parts[:3], text, name)
    if hi < lo:
        raise ValueError(f"{name} is inverted: MAX = {hi:g} < MIN = {lo:g}")
    if n == 1 and hi != lo:
        raise ValueError(f"{name}: N = 1 needs MIN = MAX, got {text!r}")
    if n > 1 and hi == lo:
        raise ValueError(f"{name}: MIN = MAX = {lo:g} with N = {n} repeats one value")
    if scale == "log":
        if lo <= 0:
            raise ValueError(f"{name} with log spacing needs MIN > 0, got {lo:g} "
                             "(use :lin for a range that starts at 0)")
        return np.geomspace(lo, hi, n)
    return np.linspace(lo, hi, n)


def parse_phases(text: str, name: str = "--phase") -> np.ndarray:
    """``MIN:MAX:N`` -> ``N`` points in [MIN, MAX) (MAX excluded: 0 and 2 pi are one phase)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{name} must be MIN:MAX:N, got {text!r}")
    lo, hi, n = _min_max_count(parts, text, name)
    if hi <= lo:
        raise ValueError(f"{name} is empty or inverted: MAX = {hi:g} <= MIN = {lo:g}")
    return lo + (hi - lo) * np.arange(n) / n


def write_dataset(ds, out: Path) -> None:
    """Write NetCDF atomically (a temp file renamed into place), so an interrupted run never
    leaves a truncated file under the final name."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    ds.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, out)


def netcdf_out(text: str) -> Path:
    """The ``--out`` path of a command that writes one NetCDF file."""
    out = Path(text)
    if out.suffix != ".nc":
        raise ValueError(f"--out must end in .nc (NetCDF), got {out}")
    return out


def check_png(text: str | None, name: str = "--plot", required: bool = False) -> None:
    """A PNG path argument; unless ``required``, empty or None means no figure was asked for."""
    if (required or text) and not (text or "").endswith(".png"):
        raise ValueError(f"{name} must end in .png, got {text!r}")


def _sweep(args) -> int:
    import jaxdea
    from jaxdea.plotting import plot_sweep

    out = netcdf_out(args.out)
    freq = parse_range(args.freq)
    model = jaxdea.load_config(args.config)
    control = jaxdea.StepControl(rtol=args.rtol)
    print(f"jaxdea sweep: {model.name}, drive {args.drive}, {freq.size} frequencies "
          f"{freq[0]:g}-{freq[-1]:g} Hz, protocol {args.protocol}, {args.cycles} cycles "
          f"(average last {args.average})", flush=True)
    ds = jaxdea.sweep(model, mass=args.mass, damping=args.damping, freq=freq, drive=args.drive,
                      phase=args.phase, cycles=args.cycles, average=args.average,
                      control=control, protocol=args.protocol, direction=args.direction,
                      tol=args.tol, early_exit=args.early_exit)
    write_dataset(ds, out)
    i = int(np.argmax(ds["P_out"].values))
    bad = int((ds["status"] != 0).sum())
    print(f"wrote {out}: P_out max {1e3 * float(ds['P_out'][i]):.3f} mW at "
          f"{float(ds['f'][i]):g} Hz; {bad} failed cell(s)")
    if args.plot:
        plot_sweep(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _powermap(args) -> int:
    import jax

    import jaxdea
    from jaxdea.mapstore import check_store_path
    from jaxdea.plotting import plot_pmax

    out = check_store_path(args.out)
    mass = parse_points(args.mass, "--mass")
    damping = parse_points(args.damping, "--damping")
    freq = parse_range(args.freq, "--freq")
    phase = parse_phases(args.phase) if args.phase is not None else None
    check_png(args.plot)
    model = jaxdea.load_config(args.config)
    n = mass.size * damping.size * freq.size * (1 if phase is None else phase.size)
    print(f"jaxdea powermap: {model.name}, drive {args.drive}, protocol {args.protocol}: "
          f"{mass.size} M x {damping.size} c x {freq.size} f"
          + (f" x {phase.size} phase" if phase is not None else "")
          + f" = {n} cells, {args.cycles} cycles (average last {args.average}), "
          + (f"{args.direction} continuation, " if args.protocol == "continuation" else "")
          + f"{len(jax.devices())} device(s)", flush=True)
    ds = jaxdea.powermap(model, mass=mass, damping=damping, freq=freq, phase=phase,
                         drive=args.drive, protocol=args.protocol, cycles=args.cycles,
                         average=args.average, control=jaxdea.StepControl(rtol=args.rtol),
                         direction=args.direction, tol=args.tol, early_exit=args.early_exit,
                         chunk_cells=args.chunk,
                         store=out, resume=args.resume, progress=not args.no_progress)
    print(f"chunks: {ds.attrs['chunks_computed']} computed, {ds.attrs['chunks_reused']} reused",
          flush=True)
    bad = int((ds["status"] != 0).sum())
    pmax = ds["P_max"]
    if bool(pmax.notnull().any()):
        flat = int(np.argmax(np.nan_to_num(pmax.values, nan=-np.inf)))
        best = dict(zip(pmax.dims, np.unravel_index(flat, pmax.shape)))
        at = {k: float(ds[k][v]) for k, v in best.items()}
        print(f"wrote {out}: P_max {1e3 * float(pmax.isel(best)):.3f} mW at "
              f"M = {1e3 * at['M']:g} g, c = {at['c']:g} N s/m"
              + (f", phase = {at['phase']:g} rad" if "phase" in at else "")
              + f", f = {float(ds['f_at_P_max'].isel(best)):g} Hz; {bad} failed cell(s)")
    else:
        print(f"wrote {out}: no cell finished with status 0; {bad} failed cell(s)")
    if args.plot:
        plot_pmax(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _plot(args) -> int:
    from jaxdea.mapstore import open_map
    from jaxdea.plotting import plot_pmax, plot_pmax_ratio, plot_pout_fc

    check_png(args.out, "--out", required=True)
    if args.kind == "ratio" and args.other is None:
        raise ValueError("--kind ratio needs --other MAP2 (the denominator map)")
    if args.kind != "ratio" and args.other is not None:
        raise ValueError("--other is only used with --kind ratio")
    if args.mass is not None and args.kind != "pout-f-c":
        raise ValueError("--mass is only used with --kind pout-f-c")
    ds = open_map(args.map)
    if args.kind == "pmax":
        plot_pmax(ds, args.out)
    elif args.kind == "pout-f-c":
        plot_pout_fc(ds, args.out, mass=args.mass)
    else:
        plot_pmax_ratio(ds, open_map(args.other), args.out)
    print(f"wrote {args.out}")
    return 0


def _protocol_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--protocol", default="paper", choices=["paper", "continuation", "periodic"],
                   help="paper: N cycles from rest per cell, mean of the last K; continuation: "
                        "the same, each f starting from the previous f's final state; periodic: "
                        "periodic steady state (settle, then Newton shooting)")
    p.add_argument("--direction", default="forward", choices=["forward", "backward"],
                   help="continuation: up (forward, as paper 000) or down the f axis")
    p.add_argument("--tol", type=float, default=1e-6,
                   help="periodic: tolerance on the scaled periodicity residual, (0, 1)")
    p.add_argument("--early-exit", type=_early_exit, default=1e-8, metavar="TOL|off",
                   help="paper/continuation: stop a cell once its trajectory is periodic to TOL "
                        "(its remaining cycles would repeat the last one; default 1e-8); "
                        "'off' runs every cell for all N cycles")


def _early_exit(text: str) -> float | None:
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--early-exit must be a tolerance in (0, 1) or 'off', got {text!r}") from None


def _lin_points(text: str, name: str) -> np.ndarray:
    """``MIN:MAX:N[:lin|:log]`` with linear spacing unless ``:log`` is given."""
    return parse_points(text + ":lin" if text.count(":") == 2 else text, name)


def _rotary_study(args) -> int:
    import jaxdea
    from jaxdea.actuators.rotary import RotaryDCDEA, ROTARY_STATUS
    from jaxdea.plotting import plot_rotary_study

    out = netcdf_out(args.out)
    check_png(args.plot)
    ri = _lin_points(args.ri, "--ri")
    d = _lin_points(args.d, "--d")
    model = jaxdea.load_config(args.config)
    if not isinstance(model, RotaryDCDEA):
        raise ValueError(f"{args.config}: rotary-study needs model = \"rotary_dcdea\"")
    if args.field is not None:
        model = model.with_field(args.field)
    print(f"jaxdea rotary-study: {ri.size} r_i x {d.size} d = {ri.size * d.size} points, "
          f"{model.field} field", flush=True)
    ds = jaxdea.rotary_study(model, ri, d)
    write_dataset(ds, out)
    th = ds["theta_deg"].values
    bad = {int(k): int((ds["status"] == k).sum()) for k in np.unique(ds["status"]) if k != 0}
    if np.isfinite(th).any():
        i, j = np.unravel_index(int(np.nanargmax(th)), th.shape)
        print(f"wrote {out}: max theta {th[i, j]:.3f} deg at r_i = {1e3 * ri[i]:g} mm, "
              f"d = {1e3 * d[j]:g} mm")
    else:
        print(f"wrote {out}: no point with a stable equilibrium")
    for k, n in bad.items():
        print(f"  {n} point(s) with status {k}: {ROTARY_STATUS[k]}")
    if args.plot:
        plot_rotary_study(ds, args.plot)
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
    _protocol_args(s)
    s.add_argument("--out", required=True, help="output NetCDF file (.nc)")
    s.add_argument("--plot", help="optional PNG: amplitude and P_out against f (Fig 6 style)")
    s.set_defaults(func=_sweep)

    m = sub.add_parser("powermap", help="power map over payload mass x damping x frequency")
    m.add_argument("config", help="TOML config, e.g. configs/dcdea_ls.toml")
    m.add_argument("--mass", required=True,
                   help="MIN:MAX:N[:log|:lin] payload masses M, kg (N points, default log)")
    m.add_argument("--damping", required=True,
                   help="MIN:MAX:N[:log|:lin] payload dampings c, N s/m (N points, default log)")
    m.add_argument("--freq", required=True, help="FMIN:FMAX:DF in Hz (inclusive)")
    m.add_argument("--phase", help="MIN:MAX:N phases of B vs A, rad: N points in [MIN, MAX) "
                                   "(drive both only)")
    m.add_argument("--drive", default="A", choices=["A", "B", "both"])
    m.add_argument("--cycles", type=int, default=100, help="drive periods per cell")
    m.add_argument("--average", type=int, default=5, help="last periods averaged")
    m.add_argument("--rtol", type=float, default=1e-6, help="solver relative tolerance")
    _protocol_args(m)
    m.add_argument("--chunk", type=int, help="cells per compiled call (default: equal chunks "
                   "of at most 4096 cells per device)")
    m.add_argument("--out", required=True, help="output store: .zarr (Zarr) or .nc (NetCDF)")
    m.add_argument("--resume", action="store_true",
                   help="continue an interrupted run of the same settings (reuse its chunks)")
    m.add_argument("--plot", help="optional PNG of P_max over M x c (paper 000 Fig 7 style)")
    m.add_argument("--no-progress", action="store_true", help="no progress bar")
    m.set_defaults(func=_powermap)

    g = sub.add_parser("plot", help="figures of a power map (paper 000 Figs 7, 9, 10)")
    g.add_argument("map", help="power-map store (.zarr or .nc)")
    g.add_argument("--kind", required=True, choices=["pmax", "pout-f-c", "ratio"],
                   help="pmax: P_max over M x c (Fig 7); pout-f-c: P_out over f x c at one M "
                        "(Fig 9); ratio: P_max of MAP / P_max of --other (Fig 10)")
    g.add_argument("--other", help="second map for --kind ratio (denominator)")
    g.add_argument("--mass", type=float, help="payload mass for pout-f-c, kg (nearest M; "
                                              "default: the M of the largest P_max)")
    g.add_argument("--out", required=True, help="output PNG")
    g.set_defaults(func=_plot)

    r = sub.add_parser("rotary-study",
                       help="steady angle of the rotational double cone over r_i x d "
                            "(paper 003 Fig 12)")
    r.add_argument("config", help="TOML config, e.g. configs/rotary_dcdea.toml")
    r.add_argument("--ri", required=True,
                   help="MIN:MAX:N[:lin|:log] inner radii r_i, m (N points, default lin)")
    r.add_argument("--d", required=True,
                   help="MIN:MAX:N[:lin|:log] half spacer lengths d, m (N points, default lin)")
    r.add_argument("--field", choices=["frozen", "literal"],
                   help="eq-9 reading (default: the config's)")
    r.add_argument("--out", required=True, help="output NetCDF file (.nc)")
    r.add_argument("--plot", help="optional PNG: contour of the angle (Fig 12 style)")
    r.set_defaults(func=_rotary_study)

    from jaxdea.calibrate_cli import add_calibrate_parser

    add_calibrate_parser(sub)
    from jaxdea.transient_cli import add_simulate_parser

    add_simulate_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxdea.config import ConfigError
    from jaxdea.sharding import use_cpu_cores
    from jaxdea.sweep import SweepError

    if argv is None:  # the command line (not a call from Python, whose JAX may be in use)
        use_cpu_cores()  # one JAX device per core: batched runs shard over all of them

    try:
        return args.func(args)
    except (ConfigError, SweepError, ValueError, NotImplementedError) as exc:
        print(f"jaxdea: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
