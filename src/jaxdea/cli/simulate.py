"""``jaxdea simulate CONFIG --signal ...``: transient of a viscoelastic model (papers 001, 002,
004) to NetCDF, with optional plots of displacement vs time and vs voltage (hysteresis)."""

from __future__ import annotations

import argparse
import math

import numpy as np

from jaxdea._checks import check_unit_interval

from .args import check_png, netcdf_out, write_dataset

SIGNALS = ("multisine", "vp1", "vp2", "vp3", "vp4", "sine")
#: The most output samples (``--cycles`` x ``--points``) one run may ask for (about 80 MB a
#: channel): a guard against a typo that would allocate gigabytes before any check.
MAX_SAMPLES = 10_000_000


def _floats(text: str | None, name: str) -> list[float] | None:
    if text is None:
        return None
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers, got {text!r}") from None


def make_signal(kind: str, *, peak: float | None, period: float | None,
                amplitudes: list[float] | None = None, freqs: list[float] | None = None):
    """Drive from CLI options. multisine: ``amplitudes``/``freqs`` (default paper 002's
    a_i = 5.5 + 0.5 i kV, f_i = 0.2 i Hz); vp1..vp4: ``peak`` (V) and ``period`` (s)
    (default 4.5 kV, 10 s); sine: ``peak`` sin(2 pi t / ``period``) (default 1 kV, 1 s).
    ``peak`` must be finite and ``period`` finite and > 0 (``ValueError`` otherwise)."""
    import jax.numpy as jnp

    from jaxdea.signals import MultiSine, Sine, voltage_pattern

    if peak is not None and not math.isfinite(peak):
        raise ValueError(f"--peak must be a finite voltage, got {peak!r}")
    if period is not None and not (math.isfinite(period) and period > 0):
        raise ValueError(f"--period = {period!r} s is outside the allowed range (0, inf)")

    if kind == "multisine":
        a = amplitudes if amplitudes is not None else [6000.0, 6500.0, 7000.0, 7500.0, 8000.0]
        f = freqs if freqs is not None else [0.2, 0.4, 0.6, 0.8, 1.0]
        return MultiSine(jnp.asarray(a, float), jnp.asarray(f, float))
    if kind.startswith("vp"):
        return voltage_pattern(kind, 4500.0 if peak is None else peak,
                               10.0 if period is None else period)
    if kind == "sine":
        return Sine(1000.0 if peak is None else peak, 1.0 / (1.0 if period is None else period))
    raise ValueError(f"--signal must be one of {', '.join(SIGNALS)}, got {kind!r}")


def _simulate(args) -> int:
    import jaxdea
    from jaxdea.plotting import plot_transient
    from jaxdea.studies.transient import transient

    out = netcdf_out(args.out)
    check_png(args.plot)
    if args.cycles < 1:
        raise ValueError(f"--cycles must be >= 1, got {args.cycles}")
    if args.points < 8:
        raise ValueError(f"--points must be >= 8 per cycle, got {args.points}")
    if args.cycles * args.points > MAX_SAMPLES:
        raise ValueError(f"--cycles x --points = {args.cycles * args.points} output samples is "
                         f"outside the allowed range [8, {MAX_SAMPLES}]")
    check_unit_interval("--rtol", args.rtol)
    model = jaxdea.load_config(args.config)
    if not hasattr(model, "vector_field") or not hasattr(model, "observables"):
        raise ValueError(f"{args.config}: 'simulate' needs a viscoelastic model "
                         f"(planar_gu2017, mass_cone_huang2020, mass_cone_nouhi)")
    signal = make_signal(args.signal, peak=args.peak, period=args.period,
                         amplitudes=_floats(args.amplitudes, "--amplitudes"),
                         freqs=_floats(args.freqs, "--freqs"))
    period = float(signal.period)
    ts = np.linspace(0.0, args.cycles * period, args.cycles * args.points + 1)
    print(f"jaxdea simulate: {args.config}, {args.signal}, {args.cycles} cycle(s) of "
          f"{period:g} s", flush=True)
    ds = transient(model, signal, ts, name=str(args.config), rtol=args.rtol)
    ds.attrs.update(signal=args.signal, period=period, cycles=args.cycles)
    write_dataset(ds, out)
    z = ds["displacement"].values
    print(f"wrote {out}: displacement {1e3 * z.min():.4f} .. {1e3 * z.max():.4f} mm"
          + ("" if ds.attrs["ok"] else " (solver FAILED: results not trustworthy)"))
    if args.plot:
        plot_transient(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0 if ds.attrs["ok"] else 1


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` command to ``sub``."""
    s = sub.add_parser("simulate", help="transient of a viscoelastic model (papers 001, 002, "
                                        "004) under a drive signal")
    s.add_argument("config", help="TOML config, e.g. configs/gu2017_final.toml")
    s.add_argument("--signal", required=True, choices=SIGNALS)
    s.add_argument("--peak", type=float, help="peak voltage, V (vp1-vp4, sine)")
    s.add_argument("--period", type=float, help="period, s (vp1-vp4, sine)")
    s.add_argument("--amplitudes", help="multisine a_i, V, comma-separated")
    s.add_argument("--freqs", help="multisine f_i, Hz, comma-separated")
    s.add_argument("--cycles", type=int, default=1, help="signal periods to simulate")
    s.add_argument("--points", type=int, default=400, help="output samples per period")
    s.add_argument("--rtol", type=float, default=1e-8, help="solver relative tolerance")
    s.add_argument("--out", required=True, help="output NetCDF file (.nc)")
    s.add_argument("--plot", help="optional PNG: displacement vs time and vs voltage")
    s.set_defaults(func=_simulate)
