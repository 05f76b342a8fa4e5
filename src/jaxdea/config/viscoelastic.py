"""TOML configs of the viscoelastic models (planar DEA of paper 004, mass cones of 001/002).

Layouts (all SI; see ``configs/gu2017_*.toml``, ``configs/huang2020_mass_cone.toml``,
``configs/nouhi_kelvin_cone.toml``)::

    model = "planar_gu2017"
    [geometry]  L1, L2, H, lam1p, lam2p, relative_permittivity
    [material]  mu0, J0, mu = [...], J = [...], tau = [...]

    model = "mass_cone_huang2020"            model = "mass_cone_nouhi"
    [geometry]  frame_radius, plate_radius, thickness, prestretch_deflection,
                relative_permittivity, density, added_mass, weight_mass, gravity,
                load = "equilibrium" | "weight"
    [material]  mu0, J0, mu, J, tau          [material] mu1, J1, mu, J, eta

Every number is checked with :class:`jaxdea.config.fields.Field` (errors name ``section.key``
and the allowed range); the unit arrays must have equal, non-zero lengths.
"""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp

from .._checks import ConfigError
from ..materials import EPS0, GentKelvinChain, GentSpringDashpot
from ..models.mass_cone import MassCone, with_load
from ..models.planar import PlanarDEA
from .fields import Field, check_top, number_list, section, table_of

PLANAR_GEOMETRY = {
    "L1": Field(0.0, math.inf, lo_open=True, unit="m"),
    "L2": Field(0.0, math.inf, lo_open=True, unit="m"),
    "H": Field(0.0, math.inf, lo_open=True, unit="m"),
    "lam1p": Field(1.0, 10.0, unit="(-)"),
    "lam2p": Field(1.0, 10.0, unit="(-)"),
    "relative_permittivity": Field(1.0, math.inf, unit="(-)"),
}
CONE_GEOMETRY = {
    "frame_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "plate_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "thickness": Field(0.0, math.inf, lo_open=True, unit="m"),
    "prestretch_deflection": Field(0.0, math.inf, lo_open=True, unit="m"),
    "relative_permittivity": Field(1.0, math.inf, unit="(-)"),
    "density": Field(0.0, math.inf, lo_open=True, unit="kg/m^3"),
    "added_mass": Field(0.0, math.inf, unit="kg"),
    "weight_mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
    "gravity": Field(0.0, math.inf, lo_open=True, unit="m/s^2"),
}
LOADS = ("equilibrium", "weight")
MAXWELL_SCALARS = {"mu0": Field(0.0, math.inf, lo_open=True, unit="Pa"),
                   "J0": Field(0.0, math.inf, lo_open=True, unit="(-)")}
KELVIN_SCALARS = {"mu1": Field(0.0, math.inf, lo_open=True, unit="Pa"),
                  "J1": Field(0.0, math.inf, lo_open=True, unit="(-)")}
MAXWELL_ARRAYS = {"mu": Field(0.0, math.inf, lo_open=True, unit="Pa"),
                  "J": Field(0.0, math.inf, lo_open=True, unit="(-)"),
                  "tau": Field(0.0, math.inf, lo_open=True, unit="s (relaxation time)")}
KELVIN_ARRAYS = {"mu": Field(0.0, math.inf, lo_open=True, unit="Pa"),
                 "J": Field(0.0, math.inf, lo_open=True, unit="(-)"),
                 "eta": Field(0.0, math.inf, lo_open=True, unit="Pa s (dashpot viscosity)")}


def _material(table: Any, scalars: dict, arrays: dict) -> dict:
    if not isinstance(table, dict):
        raise ConfigError("[material] must be a table")
    unknown = sorted(map(str, set(table) - set(scalars) - set(arrays)))
    if unknown:
        raise ConfigError(f"unknown key(s) in [material]: {', '.join(unknown)}; allowed: "
                          f"{', '.join([*scalars, *arrays])}")
    out = section({k: v for k, v in table.items() if k in scalars}, "material", scalars)
    n = None
    for key, field in arrays.items():
        out[key] = number_list(table, "material", key, field)
        if n is None:
            n = len(out[key])
        elif len(out[key]) != n:
            raise ConfigError(f"material.{key} has {len(out[key])} value(s) but "
                              f"material.{next(iter(arrays))} has {n}: one per unit")
    return out


def planar_from_config(cfg: dict) -> PlanarDEA:
    """Validated :class:`~jaxdea.models.planar.PlanarDEA` from a parsed config."""
    check_top(cfg, "planar_gu2017", ("geometry", "material"))
    geo = section(cfg["geometry"], "geometry", PLANAR_GEOMETRY)
    mat = _material(cfg["material"], MAXWELL_SCALARS, MAXWELL_ARRAYS)
    model = PlanarDEA(L1=geo["L1"], L2=geo["L2"], H=geo["H"], lam1p=geo["lam1p"],
                      lam2p=geo["lam2p"], eps=geo["relative_permittivity"] * EPS0,
                      material=GentSpringDashpot(**mat, flow="deviatoric"))
    model.check()  # ValueError -> ConfigError in jaxdea.config.model_from_dict
    return model


def mass_cone_from_config(cfg: dict) -> MassCone:
    """Validated :class:`~jaxdea.models.mass_cone.MassCone` from a parsed config."""
    kind = cfg.get("model")
    check_top(cfg, kind, ("geometry", "material"))
    table = table_of(cfg["geometry"], "geometry")
    load = table.pop("load", None)
    if load not in LOADS:
        raise ConfigError(f"geometry.load must be one of {', '.join(map(repr, LOADS))}, "
                          f"got {load!r}")
    geo = section(table, "geometry", CONE_GEOMETRY)
    if kind == "mass_cone_nouhi":
        material = GentKelvinChain(**_material(cfg["material"], KELVIN_SCALARS, KELVIN_ARRAYS))
    else:
        material = GentSpringDashpot(**_material(cfg["material"], MAXWELL_SCALARS,
                                                 MAXWELL_ARRAYS), flow="conjugate")
    if not float(geo["frame_radius"]) > float(geo["plate_radius"]):
        raise ConfigError(f"geometry.frame_radius = {float(geo['frame_radius']):g} m must exceed "
                          f"geometry.plate_radius = {float(geo['plate_radius']):g} m (allowed "
                          f"range ({float(geo['plate_radius']):g}, inf) m)")
    cone = MassCone(R=geo["frame_radius"], R0=geo["plate_radius"], d0=geo["thickness"],
                    eps=geo["relative_permittivity"] * EPS0, rho=geo["density"],
                    z1=geo["prestretch_deflection"], load=jnp.asarray(0.0),
                    added_mass=geo["added_mass"], material=material)
    cone.check()  # ValueError -> ConfigError in jaxdea.config.model_from_dict
    return with_load(cone, load, float(geo["weight_mass"]), float(geo["gravity"]))
