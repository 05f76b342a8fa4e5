"""``jaxdea rotary-study``: the steady angle of paper 003's rotational double cone over r_i x d."""

from __future__ import annotations

import argparse

import numpy as np

from .args import check_png, lin_points, netcdf_out, print_status_counts, write_dataset


def _rotary_study(args) -> int:
    import jaxdea
    from jaxdea.models.rotary import ROTARY_STATUS, RotaryDCDEA
    from jaxdea.plotting import plot_rotary_study

    out = netcdf_out(args.out)
    check_png(args.plot)
    ri = lin_points(args.ri, "--ri")
    d = lin_points(args.d, "--d")
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
    if np.isfinite(th).any():
        i, j = np.unravel_index(int(np.nanargmax(th)), th.shape)
        print(f"wrote {out}: max theta {th[i, j]:.3f} deg at r_i = {1e3 * ri[i]:g} mm, "
              f"d = {1e3 * d[j]:g} mm")
    else:
        print(f"wrote {out}: no point with a stable equilibrium")
    print_status_counts(ds["status"].values, ROTARY_STATUS, "point(s)")
    if args.plot:
        plot_rotary_study(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0



def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add the ``rotary-study`` command to ``sub``."""
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
