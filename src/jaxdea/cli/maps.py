"""``jaxdea sweep``, ``jaxdea powermap`` and ``jaxdea plot``: the cone power studies."""

from __future__ import annotations

import argparse
import contextlib
import sys

import numpy as np

from jaxdea.engine.step_control import StepControl
from jaxdea.studies.loadings import check_cone_model

from .args import (
    check_png,
    check_writable,
    netcdf_out,
    parse_phases,
    parse_points,
    parse_range,
    print_status_counts,
    protocol_args,
    write_dataset,
)
from .payload import add_payload_args, cli_payload, describe

#: What the drive cases mean (paper 000): which membranes the square wave drives.
DRIVE_HELP = ("A: membrane A only (the single cone's one membrane; the double cones' first); "
              "B: membrane B only (double cones); both: A and B, B delayed by --phase rad")

def _sweep(args) -> int:
    import jaxdea
    from jaxdea.plotting import plot_sweep

    out = netcdf_out(args.out)
    check_png(args.plot)
    freq = parse_range(args.freq)
    model = jaxdea.load_config(args.config)
    check_cone_model(model)  # before its name is printed
    control = jaxdea.StepControl(rtol=args.rtol, precision=args.precision,
                                 solver=args.solver, extrapolate=args.extrapolate)
    payload, damping = cli_payload(args)
    _need_payload(args, payload, damping)
    print(f"jaxdea sweep: {model.name}, drive {args.drive}, {freq.size} frequencies "
          f"{freq[0]:g}-{freq[-1]:g} Hz, payload {describe(payload, damping)}, protocol "
          f"{args.protocol}, {args.cycles} cycles (average last {args.average})", flush=True)
    ds = jaxdea.sweep(model, mass=args.mass, damping=damping, payload=payload, freq=freq,
                      drive=args.drive,
                      phase=args.phase, cycles=args.cycles, average=args.average,
                      control=control, protocol=args.protocol, direction=args.direction,
                      tol=args.tol, early_exit=args.early_exit)
    write_dataset(ds, out)
    ok = (ds["status"].values == 0) & ds["steady"].values & np.isfinite(ds["P_out"].values)
    bad = int((ds["status"] != 0).sum())
    if ok.any():  # the maximum among the steady cells that finished (failed: nan/inf)
        i = int(np.argmax(np.where(ok, ds["P_out"].values, -np.inf)))
        print(f"wrote {out}: P_out max {1e3 * float(ds['P_out'][i]):.3f} mW at "
              f"{float(ds['f'][i]):g} Hz (steady cells); {bad} failed cell(s)")
    else:
        print(f"wrote {out}: no steady cell finished with status 0; {bad} failed cell(s)")
    _print_failed(ds)
    if args.plot:
        plot_sweep(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _powermap(args) -> int:
    import jax

    import jaxdea
    from jaxdea.studies.mapstore import check_store_path

    out = check_writable(check_store_path(args.out), "--out", directory_ok=True)
    if args.workers is not None and args.scheduler is not None:
        raise ValueError("--workers N starts a local cluster, --scheduler ADDRESS uses an "
                         "existing one: give one of them")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    mass = parse_points(args.mass, "--mass")
    payload, damping = cli_payload(args, ranges=True)
    _need_payload(args, payload, damping)
    if payload is None:
        damping = parse_points(damping, "--damping")
        second, label = damping.size, "c"
    else:
        from jaxdea.payloads import parameters

        axis = {k: v for k, v in parameters(payload).items() if np.ndim(v) == 1}
        label = next(iter(axis), "")
        second = np.size(axis[label]) if axis else 1
    freq = parse_range(args.freq, "--freq")
    phase = parse_phases(args.phase) if args.phase is not None else None
    check_png(args.plot)
    model = jaxdea.load_config(args.config)
    check_cone_model(model)  # before its name is printed
    n = mass.size * second * freq.size * (1 if phase is None else phase.size)
    print(f"jaxdea powermap: {model.name}, drive {args.drive}, payload "
          f"{describe(payload, damping)}, protocol {args.protocol}: "
          f"{mass.size} M x {second} {label} x {freq.size} f"
          + (f" x {phase.size} phase" if phase is not None else "")
          + f" = {n} cells, {args.cycles} cycles (average last {args.average}), "
          + (f"{args.direction} continuation, " if args.protocol == "continuation" else "")
          + ("warm starts from the neighbouring payload, " if args.start == "neighbour"
             else "")
          + (f"{len(jax.devices())} {jax.devices()[0].platform.upper()} device(s)"
             if args.workers is None and args.scheduler is None
             else f"Dask cluster {args.scheduler or f'of {args.workers} local worker(s)'}"),
          flush=True)
    try:
        with _cluster_client(args) as client:
            ds = _run_powermap(jaxdea, args, model, mass, damping, freq, phase, out, client,
                               payload)
    except KeyboardInterrupt:
        print(f"\njaxdea powermap: interrupted. Finished chunks are kept in {out}.parts; "
              "to go on from them, run the same command with --resume:\n  "
              + " ".join(sys.argv if "--resume" in sys.argv else [*sys.argv, "--resume"]),
              file=sys.stderr)
        return 130
    print(f"chunks: {ds.attrs['chunks_computed']} computed, {ds.attrs['chunks_reused']} reused",
          flush=True)
    return _summarise_map(ds, out, args.plot)


@contextlib.contextmanager
def _cluster_client(args):
    """The Dask client of ``--scheduler`` / ``--workers`` (None: neither), closed on exit."""
    if args.workers is None and args.scheduler is None:
        yield None
        return
    from distributed import Client, LocalCluster

    if args.scheduler is not None:
        with Client(args.scheduler, timeout="30s") as client:
            yield client
        return
    # one single-threaded process per worker: each has its own JAX device (see cluster.md)
    with LocalCluster(n_workers=args.workers, processes=True, threads_per_worker=1,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


def _need_payload(args, payload, damping) -> None:
    """One line when the command names no payload (or, for a sweep, no mass)."""
    if payload is None and damping is None:
        raise ValueError("--damping is missing: give --damping (N s/m, the linear dashpot), a "
                         "payload flag (--quadratic, --coulomb, --load-stiffness, --tilt, ...) "
                         "or a [payload] table in the config")
    if args.mass is None and (payload is None or float(np.sum(payload.mass)) == 0.0):
        raise ValueError("--mass is missing: give the payload mass (kg, >= 0) or a [payload] "
                         "table with its mass in the config")


def _run_powermap(jaxdea, args, model, mass, damping, freq, phase, out, client=None,
                  payload=None):
    return jaxdea.powermap(model, mass=mass, damping=damping, payload=payload, freq=freq,
                           phase=phase,
                           drive=args.drive, protocol=args.protocol, cycles=args.cycles,
                           average=args.average,
                           control=jaxdea.StepControl(rtol=args.rtol, precision=args.precision,
                                                      solver=args.solver,
                                                      extrapolate=args.extrapolate),
                           direction=args.direction, tol=args.tol, early_exit=args.early_exit,
                           start=args.start, chunk_cells=args.chunk, store=out, resume=args.resume,
                           progress=not args.no_progress, client=client)


def _print_failed(ds) -> None:
    """The failed cells by status code, with what each code means, then the finished cells
    that are not steady."""
    from jaxdea.engine.metrics import STATUS

    print_status_counts(ds["status"].values, STATUS)
    _print_not_steady(ds)
    _print_coexisting(ds)


def _print_not_steady(ds) -> None:
    """The count of finished (status 0) cells whose last cycles are not periodic."""
    from jaxdea.engine.metrics import STEADY_RESIDUAL

    if "steady" not in ds:  # an older store
        return
    n = int(((ds["status"] == 0) & ~ds["steady"]).sum())
    if n:
        print(f"{n} cell(s) not steady (periodicity residual above {STEADY_RESIDUAL:g}): their "
              "averages are not a steady-state power")


def _print_coexisting(ds) -> None:
    """The count of cells of a warm-started map where a second stable orbit was found."""
    if "coexist" not in ds:  # from rest, or an older store
        return
    n = int(ds["coexist"].sum())
    if n:
        print(f"{n} cell(s) with a second stable orbit (variable 'coexist'): the map reports "
              "the branch continued from the heavier loads; --start rest gives the from-rest "
              "orbits")


def _summarise_map(ds, out, plot) -> int:
    from jaxdea.plotting import law_dim, plot_pmax

    bad = int((ds["status"] != 0).sum())
    pmax = ds["P_max"]
    if bool(pmax.notnull().any()):
        flat = int(np.argmax(np.nan_to_num(pmax.values, nan=-np.inf)))
        best = dict(zip(pmax.dims, np.unravel_index(flat, pmax.shape)))
        at = {k: float(ds[k][v]) for k, v in best.items()}
        law = law_dim(ds)
        unit = ds[law].attrs.get("units", "")
        print(f"wrote {out}: P_max (steady cells) {1e3 * float(pmax.isel(best)):.3f} mW at "
              f"M = {1e3 * at['M']:g} g, {law} = {at[law]:g} {unit}"
              + (f", phase = {at['phase']:g} rad" if "phase" in at else "")
              + f", f = {float(ds['f_at_P_max'].isel(best)):g} Hz; {bad} failed cell(s)")
    else:
        print(f"wrote {out}: no steady cell finished with status 0; {bad} failed cell(s)")
    _print_failed(ds)
    if plot and bool(pmax.notnull().any()):
        plot_pmax(ds, plot)
        print(f"wrote {plot}")
    elif plot:
        print(f"no plot written to {plot}: no steady cell finished with status 0",
              file=sys.stderr)
        return 1
    return 0


def _plot(args) -> int:
    from jaxdea.plotting import plot_pmax, plot_pmax_ratio, plot_pout_fc
    from jaxdea.studies.mapstore import open_map

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



def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add the ``sweep``, ``powermap`` and ``plot`` commands to ``sub``."""
    s = sub.add_parser("sweep", help="frequency sweep of one payload (paper 000 protocol)")
    s.add_argument("config", help="TOML config, e.g. configs/dcdea_ls.toml")
    s.add_argument("--mass", type=float, help="payload mass M, kg (default: the config's "
                   "[payload] mass)")
    s.add_argument("--damping", type=float, help="payload damping c, N s/m (the linear "
                   "dashpot; with a payload law its viscous term)")
    add_payload_args(s, ranges=False)
    s.add_argument("--freq", required=True, help="FMIN:FMAX:DF in Hz (inclusive)")
    s.add_argument("--drive", default="A", choices=["A", "B", "both"], help=DRIVE_HELP)
    s.add_argument("--phase", type=float, default=0.0, help="phase of B vs A, rad [0, 2 pi)")
    s.add_argument("--cycles", type=int, default=100, help="drive periods per frequency")
    s.add_argument("--average", type=int, default=5, help="last periods averaged")
    s.add_argument("--rtol", type=float, default=StepControl().rtol,
                   help="solver relative tolerance")
    protocol_args(s)
    s.add_argument("--out", required=True, help="output NetCDF file (.nc)")
    s.add_argument("--plot", help="optional PNG: amplitude and P_out against f (Fig 6 style)")
    s.set_defaults(func=_sweep)

    m = sub.add_parser("powermap", help="power map over payload mass x damping x frequency")
    m.add_argument("config", help="TOML config, e.g. configs/dcdea_ls.toml")
    m.add_argument("--mass", required=True,
                   help="MIN:MAX:N[:log|:lin] payload masses M, kg (N points, default log)")
    m.add_argument("--damping",
                   help="MIN:MAX:N[:log|:lin] payload dampings c, N s/m (N points, default log); "
                        "with a payload law a number or a range (its viscous term)")
    add_payload_args(m, ranges=True)
    m.add_argument("--freq", required=True, help="FMIN:FMAX:DF in Hz (inclusive)")
    m.add_argument("--phase", help="MIN:MAX:N phases of B vs A, rad: N points in [MIN, MAX) "
                                   "(drive both only)")
    m.add_argument("--drive", default="A", choices=["A", "B", "both"], help=DRIVE_HELP)
    m.add_argument("--cycles", type=int, default=100, help="drive periods per cell")
    m.add_argument("--average", type=int, default=5, help="last periods averaged")
    m.add_argument("--rtol", type=float, default=StepControl().rtol,
                   help="solver relative tolerance")
    protocol_args(m)
    m.add_argument("--start", default="rest", choices=["rest", "neighbour"],
                   help="periodic: every cell from rest, or from its neighbouring payload's "
                        "orbit along the second axis (heaviest load first; chord iterations; "
                        "reports the continued branch where responses coexist)")
    m.add_argument("--chunk", type=int, help="cells per compiled call (default: equal chunks "
                   "of at most 4096 cells per device; on a Dask cluster ~4 chunks per worker, "
                   "256-4096 cells)")
    m.add_argument("--out", required=True, help="output store: .zarr (Zarr) or .nc (NetCDF)")
    m.add_argument("--resume", action="store_true",
                   help="continue an interrupted run of the same settings (reuse its chunks)")
    m.add_argument("--plot", help="optional PNG of P_max over M x c (paper 000 Fig 7 style)")
    m.add_argument("--workers", type=int, help="run the chunks on a local Dask cluster of N "
                   "single-threaded worker processes (one JAX device each; N = cores)")
    m.add_argument("--scheduler", help="run the chunks on an existing Dask cluster: its "
                   "scheduler address, e.g. tcp://10.0.0.5:8786 (workers must see --out)")
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
