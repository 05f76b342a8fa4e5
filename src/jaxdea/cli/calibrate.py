"""``jaxdea calibrate CONFIG --data FILE --fit a,b,... --method ... --out fitted.toml``."""

from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path

from .args import check_png, check_writable
from .payload import add_payload_args, cli_payload


def parse_bounds(text: str | None) -> dict[str, tuple[float, float]]:
    """``name=LO:HI,name2=LO:HI`` -> ``{name: (LO, HI)}``."""
    out: dict[str, tuple[float, float]] = {}
    if not text:
        return out
    for item in text.split(","):
        name, sep, rng = item.partition("=")
        lo, sep2, hi = rng.partition(":")
        if not (sep and sep2 and name.strip()):
            raise ValueError(f"--bounds must be NAME=LO:HI[,NAME=LO:HI...], got {item!r}")
        if name.strip() in out:
            raise ValueError(f"--bounds gives {name.strip()} twice; give each parameter once")
        try:
            out[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise ValueError(f"--bounds {item!r}: LO and HI must be numbers") from None
    return out


def _calibrate(args) -> int:
    import jaxdea
    from jaxdea.calibration import (
        FrequencyResponse,
        calibrate,
        frequency_response,
        get_params,
        load_data,
        make_params,
        write_fitted_config,
    )
    from jaxdea.calibration.predictors import Loaded
    from jaxdea.models import Model
    from jaxdea.plotting import plot_fit

    out = Path(args.out)
    if out.suffix != ".toml":
        raise ValueError(f"--out must end in .toml, got {out}")
    check_writable(out, "--out")  # before the fit: not a folder, not a user's file
    check_png(args.plot)
    if args.maxiter is not None and args.maxiter < 1:
        raise ValueError(f"--maxiter = {args.maxiter} is outside the allowed range [1, inf)")
    model = jaxdea.load_config(args.config)
    data = load_data(args.data)
    fit = [n.strip() for n in args.fit.split(",") if n.strip()]
    bounds = parse_bounds(args.bounds)
    # the payload law of the measurements: the config's [payload] table and the flags (its
    # mass and, for the dashpot, its damping are the data's columns)
    payload, _ = cli_payload(argparse.Namespace(**{**vars(args), "damping": None,
                                                   "mass": None}))
    target = model
    if payload is not None:
        if not (isinstance(data, FrequencyResponse) and isinstance(model, Model)):
            raise ValueError("a payload law (a [payload] table or payload flags) is for a cone "
                             "fitted to a frequency response")
        target = Loaded(model, payload.with_mass(0.0))
    law_fit = [n for n in fit if n.startswith("payload.")]
    if law_fit:  # the fitted law values go back into the config's [payload] table
        import tomllib

        from jaxdea.calibration.fitted_toml import config_keys
        config_keys(tomllib.loads(Path(args.config).read_text()), law_fit)
    start = get_params(target, fit)
    if args.method == "de":  # DE needs a box: default one decade either side of the start
        for given, (name, v) in zip(fit, start.items()):
            short = [k for k in bounds if k in (given, name) or name.endswith("." + k)]
            if not short:
                if not (v > 0 and math.isfinite(v)):
                    raise ValueError(f"--method de needs --bounds for {given} (start {v:g})")
                bounds[given] = (v / 10.0, v * 10.0)
    make_params(target, fit, bounds)  # validate before any compilation
    predict = None
    if isinstance(data, FrequencyResponse) and isinstance(model, Model):
        predict = functools.partial(frequency_response, cycles=args.cycles,
                                    average=args.average)
    de_options = {"popsize": args.popsize} if args.popsize is not None else None
    print(f"jaxdea calibrate: {getattr(model, 'name', type(model).__name__)}, "
          f"{type(data).__name__} {args.data}, fit {', '.join(start)}, method {args.method}",
          flush=True)
    res = calibrate(model, data, fit, bounds=bounds or None, method=args.method,
                    loss=args.loss, seed=args.seed, predict=predict, maxiter=args.maxiter,
                    de_options=de_options, curvature=not args.no_curvature, payload=payload,
                    progress=not args.no_progress)
    print(res.summary())
    header = (f"fitted by: jaxdea calibrate --method {args.method} --loss {args.loss} "
              f"--data {args.data}\nloss {res.loss:.6g}, e_rms {res.e_rms:.3g} %, "
              f"e_m {res.e_m:.3g} %, {res.n_evals} model evaluations")
    write_fitted_config(args.config, out, res.params, header=header)
    jaxdea.load_config(out)  # loads like any other config
    print(f"wrote {out}")
    if args.plot:
        plot_fit(res, data, args.plot)
        print(f"wrote {args.plot}")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``calibrate`` command to ``sub``."""
    c = sub.add_parser("calibrate", help="fit model parameters to measured data "
                                         "(L-BFGS, Adam, Gauss-Newton or differential evolution)")
    c.add_argument("config", help="TOML config whose parameters are the start values")
    c.add_argument("--data", required=True,
                   help="measured data (.csv or .nc): a time series (t, voltage, displacement"
                        "[, force]) or a frequency response (f, amplitude and/or P_out, mass, "
                        "damping); units in the header, e.g. 'f [Hz]'")
    c.add_argument("--fit", required=True,
                   help="comma-separated parameters to fit: paths or unique suffixes, e.g. "
                        "dielectric.mu_A,dielectric.tau, or a payload law's payload.NAME "
                        "(needs the config's [payload] table to hold it)")
    c.add_argument("--method", default="lbfgs", choices=["lbfgs", "adam", "lm", "de"])
    c.add_argument("--loss", default="mse", choices=["mse", "relative", "log"])
    c.add_argument("--bounds", help="NAME=LO:HI,... in SI units (de default: start/10:start*10)")
    c.add_argument("--seed", type=int, default=0, help="random seed (de)")
    c.add_argument("--maxiter", type=int, help="iterations (generations for de)")
    c.add_argument("--popsize", type=int, help="de population (default 240, paper 001)")
    c.add_argument("--cycles", type=int, default=20,
                   help="frequency responses: drive periods from rest per frequency")
    c.add_argument("--average", type=int, default=5,
                   help="frequency responses: last periods averaged")
    c.add_argument("--no-curvature", action="store_true",
                   help="skip the Gauss-Newton curvature / covariance at the optimum")
    add_payload_args(c, ranges=False)
    c.add_argument("--out", required=True, help="fitted config (.toml; fitted payload-law "
                   "values, --fit payload.NAME, go to its [payload] table)")
    c.add_argument("--plot", help="optional PNG: measured vs model")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=_calibrate)
    return c
