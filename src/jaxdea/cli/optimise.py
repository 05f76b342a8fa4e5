"""``jaxdea optimise CONFIG --vary NAME=LO:HI ... --objective pmax|power|efficiency --out
design.toml``: bounded multi-start design optimisation of steady-state power
(:func:`jaxdea.optimise`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .args import check_png, check_writable
from .payload import add_payload_args, cli_payload

OBJECTIVES = ("pmax", "power", "efficiency")
PAYLOAD = ("mass", "damping")


def parse_vary(items: list[str]) -> dict[str, tuple[float, float]]:
    """The repeated ``--vary NAME=LO:HI`` values -> ``{NAME: (LO, HI)}`` (finite, LO < HI,
    each NAME once); ``ValueError`` naming ``--vary`` and the expected form otherwise."""
    out: dict[str, tuple[float, float]] = {}
    for item in items:
        name, sep, rng = item.partition("=")
        parts = rng.split(":")
        name = name.strip()
        if not (sep and name and len(parts) == 2):
            raise ValueError(f"--vary must be NAME=LO:HI, e.g. actuator.spring_stiffness="
                             f"100:2000, got {item!r}")
        try:
            lo, hi = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"--vary {item!r}: LO and HI must be numbers (NAME=LO:HI)") from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"--vary {item!r}: LO and HI must be finite")
        if not lo < hi:
            raise ValueError(f"--vary {item!r}: LO = {lo:g} must be < HI = {hi:g}")
        if name in out:
            raise ValueError(f"--vary gives {name} twice; give each parameter once")
        out[name] = (lo, hi)
    return out


def parse_band(text: str) -> tuple[float, float]:
    """``F_LO:F_HI`` -> ``(F_LO, F_HI)`` in Hz with ``0 < F_LO < F_HI`` finite."""
    from jaxdea import JaxdeaError
    from jaxdea.studies.design import check_band

    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        band = (float(parts[0]), float(parts[1]))
    except ValueError:
        raise ValueError(f"--band must be F_LO:F_HI in Hz, e.g. 40:200, got {text!r}") from None
    try:
        return check_band(band)
    except JaxdeaError as e:
        raise ValueError(f"--{e}") from None


def _check_objective(args) -> tuple[float, float] | None:
    """The band of ``--objective pmax`` (None for the others, which need ``--freq``)."""
    if args.objective == "pmax":
        if args.band is None:
            raise ValueError("--objective pmax needs --band F_LO:F_HI (Hz), the band its "
                             "peak power is searched in")
        if args.freq is not None:
            raise ValueError("--freq is only used with --objective power or efficiency "
                             "(pmax searches --band)")
        return parse_band(args.band)
    if args.freq is None:
        raise ValueError(f"--objective {args.objective} needs --freq F (Hz)")
    if args.band is not None:
        raise ValueError("--band is only used with --objective pmax")
    if not (math.isfinite(args.freq) and args.freq > 0):
        raise ValueError(f"--freq = {args.freq:g} Hz is outside the allowed range (0, inf)")
    return None


def _check_numbers(args, vary, payload=None) -> None:
    for name in PAYLOAD:
        if payload is not None and (name == "damping" or float(payload.mass) > 0):
            continue  # the payload law carries them
        if getattr(args, name) is None and name not in vary:
            raise ValueError(f"--{name} is needed unless it is varied (--vary {name}=LO:HI)")
    if "freq" in vary:
        raise ValueError("--vary freq: the frequency cannot be varied; --freq or --band "
                         "sets it")
    if args.starts < 1:
        raise ValueError(f"--starts = {args.starts} is outside the allowed range [1, inf)")
    if args.maxiter < 0:
        raise ValueError(f"--maxiter = {args.maxiter} is outside the allowed range [0, inf)")
    if not (math.isfinite(args.max_field) and args.max_field > 0):
        raise ValueError(f"--max-field = {args.max_field:g} V/m is outside the allowed range "
                         "(0, inf)")


def _start_is_config(model, vary, mapping, args, payload=None) -> bool:
    """Whether the first start is the config's design (all its values inside the bounds)."""
    from jaxdea.params import get_params
    from jaxdea.studies.builder import LAW, law_value

    for name, (lo, hi) in vary.items():
        if name.startswith(LAW):
            v = law_value(payload, name)
        elif name == "mass" and args.mass is None and payload is not None:
            v = float(payload.mass)
        else:
            v = (getattr(args, name) if name in PAYLOAD
                 else next(iter(get_params(model, [mapping[name]]).values())))
        if v is None or not lo <= v <= hi:
            return False
    return True


def _what(objective: str, result, args, band) -> str:
    """The objective at the optimum, in words and units."""
    if objective == "pmax":
        return (f"P_max over {band[0]:g}-{band[1]:g} Hz = {1e3 * result.objective:.6g} mW at "
                f"{result.f_at_P_max:.4g} Hz")
    if objective == "power":
        return f"P_out at {args.freq:g} Hz = {1e3 * result.objective:.6g} mW"
    return f"efficiency at {args.freq:g} Hz = {1e2 * result.objective:.6g} %"


def _optimise(args) -> int:
    import jaxdea
    from jaxdea.plotting import plot_optimise
    from jaxdea.studies.design import resolve
    from jaxdea.studies.loadings import check_cone_model

    out = Path(args.out)
    if out.suffix != ".toml":
        raise ValueError(f"--out must end in .toml, got {out}")
    check_writable(out, "--out")
    check_png(args.plot)
    vary = parse_vary(args.vary)
    band = _check_objective(args)
    payload, damping = cli_payload(args)
    _check_numbers(args, vary, payload)
    model = jaxdea.load_config(args.config)
    check_cone_model(model)
    try:
        mapping = resolve(model, list(vary), payload)
    except jaxdea.SweepError as exc:
        raise ValueError(f"--vary: {exc}") from None
    from_config = _start_is_config(model, vary, mapping, args, payload)
    print(f"jaxdea optimise: {model.name}, objective {args.objective} "
          + (f"over {band[0]:g}-{band[1]:g} Hz" if band else f"at {args.freq:g} Hz")
          + f", drive {args.drive}, vary {', '.join(vary)}: {args.starts} start(s), at most "
          f"{args.maxiter} iteration(s)", flush=True)
    result = jaxdea.optimise(model, vary, args.objective, mass=args.mass, damping=damping,
                             payload=payload,
                             band=band, freq=args.freq, drive=args.drive, phase=args.phase,
                             max_field=args.max_field, starts=args.starts, seed=args.seed,
                             maxiter=args.maxiter, progress=not args.no_progress)
    result.to_toml(out)
    jaxdea.load_config(out)  # loads like any other config
    print(f"wrote {out}")
    print("optimum:")
    for name, v in result.values.items():
        print(f"  {name} = {v:.10g}")
    k, unit = (1e2, "%") if args.objective == "efficiency" else (1e3, "mW")
    start = result.start_objective
    gain = (f"{100 * (result.objective - start) / abs(start):+.2f} %"
            if math.isfinite(start) and start != 0 else "n/a")
    print(f"objective: {_what(args.objective, result, args, band)}")
    print(f"start: {k * start:.6g} {unit} ("
          + ("the config's design" if from_config else "first start: the config's design is "
             "outside the bounds") + f"); gain {gain}")
    print(f"nominal field: {result.field / 1e6:.4g} MV/m (limit {args.max_field / 1e6:g} MV/m)")
    print("active: " + ("; ".join(result.active) if result.active
                        else "none (inside the bounds, below the field limit)"))
    print("converged: yes (" + {"gradient": "projected gradient below its tolerance",
                                "step": "step length below 1e-7 of the bounds"}[
        result.stopped] + ")" if result.converged else
          f"converged: no: stopped at --maxiter {args.maxiter} iterations with the gradient "
          "not yet small (raise --maxiter)")
    if args.plot:
        plot_optimise(result, args.plot, objective=args.objective)
        print(f"wrote {args.plot}")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``optimise`` command to ``sub``."""
    o = sub.add_parser("optimise", help="maximise steady-state power or efficiency over "
                                        "bounded design parameters (multi-start, gradient)")
    o.add_argument("config", help="TOML config of a cone, the start design, e.g. "
                                  "configs/dcdea_ls.toml")
    o.add_argument("--vary", action="append", required=True, metavar="NAME=LO:HI",
                   help="a parameter to vary and its bounds, SI units (repeat for more): a "
                        "model path or unique suffix, e.g. actuator.spring_stiffness=100:2000, "
                        "membrane.prestretch=1.05:1.6, mass / damping, or a payload law's "
                        "payload.NAME (e.g. payload.quadratic=0.1:10)")
    o.add_argument("--objective", default="pmax", choices=OBJECTIVES,
                   help="pmax: peak P_out over --band; power: P_out at --freq; efficiency: "
                        "P_out / P_in at --freq")
    o.add_argument("--mass", type=float, help="payload mass M, kg (start value if varied)")
    o.add_argument("--damping", type=float,
                   help="payload damping c, N s/m (start value if varied)")
    add_payload_args(o, ranges=False)
    o.add_argument("--band", metavar="F_LO:F_HI", help="pmax: frequency band, Hz")
    o.add_argument("--freq", type=float, help="power, efficiency: drive frequency, Hz")
    o.add_argument("--drive", default="A", choices=["A", "B", "both"],
                   help="A, B or both membranes driven (single cone: A)")
    o.add_argument("--phase", type=float, help="drive both: phase of B vs A, rad [0, 2 pi)")
    o.add_argument("--max-field", type=float, default=80e6,
                   help="largest nominal field voltage / thickness at the static equilibrium, "
                        "V/m")
    o.add_argument("--starts", type=int, default=8,
                   help="starts: the config's design, then a Latin hypercube")
    o.add_argument("--seed", type=int, default=0, help="random seed of the Latin hypercube")
    o.add_argument("--maxiter", type=int, default=20, help="most ascent iterations")
    o.add_argument("--out", required=True, help="optimised config (.toml)")
    o.add_argument("--plot", help="optional PNG: the objective of every start per iteration")
    o.add_argument("--no-progress", action="store_true", help="no progress bar")
    o.set_defaults(func=_optimise)
    return o
