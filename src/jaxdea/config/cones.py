"""Loader of the square-wave cones of paper 000 (``scdea_ls``, ``dcdea_rr``, ``dcdea_ls``).

Layout (SI; see ``configs/scdea_ls.toml``)::

    model = "dcdea_ls"
    [membrane]  inner_radius, outer_radius, thickness, prestretch, relative_permittivity,
                electrode_thickness, electrode_resistance
    [membrane.dielectric]  mu_A, J_A, mu_B, J_B, tau      (GentMaxwell)
    [membrane.electrode]   mu_A, J_A, mu_B, J_B, tau
    [actuator]  disk_mass and the configuration's own fields (ACTUATOR_FIELDS)
    [drive]     voltage, duty, and optionally breakdown_field (V/m, default 100e6)
    [payload]   optional: the driven load (:mod:`jaxdea.config.payload`)
"""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp

from .._checks import ConfigError
from ..materials import GentMaxwell, gent_denominator
from ..membrane import BREAKDOWN_FIELD, ConeMembrane
from ..models import DCDEA_LS, DCDEA_RR, SCDEA_LS, ConeActuator, Model
from .fields import Field, check_top, section, subtables
from .payload import payload_from_config

MEMBRANE_FIELDS = {
    "inner_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "outer_radius": Field(0.0, math.inf, lo_open=True, unit="m"),
    "thickness": Field(0.0, math.inf, lo_open=True, unit="m"),
    "prestretch": Field(1.0, 10.0, unit="(-)"),
    "relative_permittivity": Field(1.0, math.inf, unit="(-)"),
    "electrode_thickness": Field(0.0, math.inf, unit="m"),
    "electrode_resistance": Field(0.0, math.inf, lo_open=True, unit="ohm"),
}
MATERIAL_FIELDS = {
    "mu_A": Field(0.0, math.inf, lo_open=True, unit="Pa"),
    "J_A": Field(0.0, math.inf, lo_open=True, unit="(-)"),
    "mu_B": Field(0.0, math.inf, lo_open=True, unit="Pa"),
    "J_B": Field(0.0, math.inf, lo_open=True, unit="(-)"),
    "tau": Field(0.0, math.inf, lo_open=True, unit="s"),
}
ACTUATOR_FIELDS = {
    "scdea_ls": {
        "disk_mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
        "spring_stiffness": Field(0.0, math.inf, unit="N/m"),
        "deflection": Field(0.0, math.inf, lo_open=True, unit="m"),
    },
    "dcdea_rr": {
        "disk_mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
        "rod_length": Field(0.0, math.inf, lo_open=True, unit="m"),
    },
    "dcdea_ls": {
        "disk_mass": Field(0.0, math.inf, lo_open=True, unit="kg"),
        "spring_stiffness": Field(0.0, math.inf, unit="N/m"),
        "deflection": Field(0.0, math.inf, lo_open=True, unit="m"),
    },
}
DRIVE_FIELDS = {
    "voltage": Field(0.0, math.inf, unit="V"),
    "duty": Field(0.0, 1.0, lo_open=True, hi_open=True, unit="(-)"),
    # optional (default BREAKDOWN_FIELD): the film's dielectric breakdown field, checked only
    "breakdown_field": Field(0.0, math.inf, lo_open=True, unit="V/m"),
}


def parameter_range(model: Model, path: str) -> Field | None:
    """The config's allowed range of the cone parameter at ``path`` (a full path of
    :func:`jaxdea.parameter_names`, an element index ``[i]`` ignored), or None."""
    path = path.split("[")[0]
    head, _, key = path.rpartition(".")
    if head in ("actuator.membrane.dielectric", "actuator.membrane.electrode"):
        return MATERIAL_FIELDS.get(key)
    if head == "actuator.membrane":
        return MEMBRANE_FIELDS.get(key)
    if head == "actuator":
        return ACTUATOR_FIELDS.get(model.actuator.name, {}).get(key)
    return DRIVE_FIELDS.get(key) if not head else None


ACTUATOR_CLASSES: dict[str, type[ConeActuator]] = {
    "scdea_ls": SCDEA_LS,
    "dcdea_rr": DCDEA_RR,
    "dcdea_ls": DCDEA_LS,
}


def cone_from_config(cfg: dict[str, Any]) -> Model:
    """Validated cone :class:`~jaxdea.models.Model` from a parsed config dictionary."""
    check_top(cfg, cfg["model"], ("membrane", "actuator", "drive"), ("payload",))
    payload_from_config(cfg)  # an optional [payload] table: checked here, read by load_payload
    kind = cfg["model"]

    flat, nested = subtables(cfg["membrane"], "membrane", ("dielectric", "electrode"))
    geo = section(flat, "membrane", MEMBRANE_FIELDS)
    if not geo["outer_radius"] > geo["inner_radius"]:
        raise ConfigError(
            f"membrane.outer_radius = {float(geo['outer_radius']):g} m must be greater than "
            f"membrane.inner_radius = {float(geo['inner_radius']):g} m (allowed range "
            f"({float(geo['inner_radius']):g}, inf) m)"
        )
    dielectric = GentMaxwell(**section(nested["dielectric"], "membrane.dielectric",
                                        MATERIAL_FIELDS))
    electrode = GentMaxwell(**section(nested["electrode"], "membrane.electrode",
                                       MATERIAL_FIELDS))
    membrane = ConeMembrane(**geo, dielectric=dielectric, electrode=electrode)
    act = section(cfg["actuator"], "actuator", ACTUATOR_FIELDS[kind])
    actuator = ACTUATOR_CLASSES[kind](membrane=membrane, **act)
    table = cfg["drive"]
    if isinstance(table, dict):  # breakdown_field is optional
        table = {"breakdown_field": BREAKDOWN_FIELD, **table}
    drive = section(table, "drive", DRIVE_FIELDS)
    _check_rest_state(actuator)
    return Model(actuator=actuator, voltage=drive["voltage"], duty=drive["duty"], name=kind,
                 breakdown_field=float(drive["breakdown_field"]))


def _check_rest_state(actuator: ConeActuator) -> None:
    """The Gent springs must be below lock-up at the static equilibrium (J above I1 - 3)."""
    mem = actuator.membrane
    design = getattr(actuator, "deflection", None)
    if design is not None:  # the spring preload is computed at the design deflection d0
        d = jnp.stack([design, -design])
        _check_gent(mem, d)
    q = actuator.equilibrium()
    if not bool(jnp.all(jnp.isfinite(q))):
        raise ConfigError("no static equilibrium found: check actuator and membrane values")
    _check_gent(mem, actuator.deflections(q))


def _check_gent(mem: ConeMembrane, d) -> None:
    """Both equilibrium Gent springs must be below lock-up at deflections ``d``."""
    lam_m1, lam_m2, lam_el1, *_ = mem.kinematics(d)
    checks = {
        "membrane.dielectric.J_A": (mem.dielectric.J_A, lam_m1, lam_m2),
        "membrane.electrode.J_A": (mem.electrode.J_A, lam_el1, 1.0),
    }
    for name, (J, l1, l2) in checks.items():
        denom = gent_denominator(l1, l2, J)
        if not bool(jnp.all(denom > 0)):
            i1 = float(jnp.max(J * (1.0 - denom)))  # I1 - 3
            raise ConfigError(
                f"{name} is below the stretch invariant at rest (I1 - 3 = {i1:.3g}): the Gent "
                f"spring is locked up; allowed range ({i1:.3g}, inf)"
            )


