"""Loader of the rotational double cone of paper 003 (``configs/rotary_dcdea.toml``)."""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp

from .._checks import ConfigError
from ..models.rotary import (
    FIELD_MODES,
    OK,
    ROTARY_STATUS,
    OgdenTypeDE,
    RotaryDCDEA,
    check_geometry,
    equilibrium,
)
from .fields import Field, check_top, number_list, section, table_of

GEOMETRY_FIELDS = {
    "inner_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "outer_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "spacer_half_length": Field(0.0, math.inf, lo_open=True, unit="m"),
    "spacer_frame_half_thickness": Field(0.0, math.inf, unit="m"),
    "frame_half_thickness": Field(0.0, math.inf, unit="m"),
    "thickness": Field(0.0, math.inf, lo_open=True, unit="m"),
}
MATERIAL_SCALARS = {
    "relative_permittivity": Field(1.0, math.inf, unit="(-)"),
    "eta_v0": Field(0.0, math.inf, unit="Pa s"),
}
MATERIAL_LISTS = {
    "alpha": Field(-100.0, 100.0, unit="(-)"),
    "beta": Field(unit="Pa"),
    "gamma": Field(unit="Pa"),
}
SPACER_FIELDS = {
    "mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
    "inertia": Field(0.0, math.inf, lo_open=True, unit="kg m^2"),
    "gravity": Field(0.0, 100.0, unit="m/s^2"),
}
DRIVE_SCALARS = {
    "field_max": Field(0.0, math.inf, unit="V/m"),
    "filter_time": Field(0.0, math.inf, lo_open=True, unit="s"),
}
PATTERN_FIELD = Field(0.0, math.inf, unit="x eq-30 voltage")


def rotary_from_config(cfg: dict[str, Any]) -> RotaryDCDEA:
    """Validated :class:`RotaryDCDEA` from a parsed ``configs/rotary_dcdea.toml``."""
    check_top(cfg, "rotary_dcdea", ("geometry", "material", "spacer", "drive"), ("field",))
    field = cfg.get("field", "frozen")
    if field not in FIELD_MODES:
        raise ConfigError(f"field = {field!r} is not one of {', '.join(FIELD_MODES)}")

    geo = section(cfg["geometry"], "geometry", GEOMETRY_FIELDS)
    mat_tab = table_of(cfg["material"], "material")
    lists = {k: number_list(mat_tab, "material", k, fld) for k, fld in MATERIAL_LISTS.items()}
    if not len({int(v.shape[0]) for v in lists.values()}) == 1:
        raise ConfigError("material.alpha, material.beta and material.gamma must have the same "
                          "number of terms N")
    if not bool(jnp.all(lists["alpha"] != 0)):
        raise ConfigError("material.alpha entries must be non-zero, allowed range "
                          "[-100, 0) or (0, 100]")
    mat = section({k: v for k, v in mat_tab.items() if k not in MATERIAL_LISTS}, "material",
                   MATERIAL_SCALARS)
    spacer = section(cfg["spacer"], "spacer", SPACER_FIELDS)
    drv_tab = table_of(cfg["drive"], "drive")
    pattern = number_list(drv_tab, "drive", "pattern", PATTERN_FIELD, n=4)
    drv = section({k: v for k, v in drv_tab.items() if k != "pattern"}, "drive", DRIVE_SCALARS)

    model = RotaryDCDEA(
        r_i=geo["inner_radius"], r_o=geo["outer_radius"], d=geo["spacer_half_length"],
        f=geo["spacer_frame_half_thickness"], h=geo["frame_half_thickness"], z0=geo["thickness"],
        mass=spacer["mass"], inertia=spacer["inertia"], gravity=spacer["gravity"],
        material=OgdenTypeDE(alpha=tuple(float(a) for a in lists["alpha"]), beta=lists["beta"],
                             gamma=lists["gamma"], eps_r=mat["relative_permittivity"],
                             eta_v0=mat["eta_v0"]),
        field_max=drv["field_max"], pattern=pattern, filter_time=drv["filter_time"], field=field,
    )
    check_geometry(model)
    rest = equilibrium(model, jnp.zeros(4))
    if int(rest.status) != OK:
        raise ConfigError("no stable unactuated equilibrium (" + ROTARY_STATUS[int(rest.status)]
                          + "): check [geometry] and [material] values")
    return model

