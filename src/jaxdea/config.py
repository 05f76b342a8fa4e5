"""TOML configs -> validated model objects.

Every field is checked before any computation: an unknown key, a missing key, a non-finite
value or a value outside its allowed range raises :class:`ConfigError` naming the field
(``section.key``) and the allowed range. Values are SI units.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import importlib

import equinox as eqx
import jax.numpy as jnp

from .actuators import DCDEA_LS, DCDEA_RR, SCDEA_LS, ConeActuator
from .materials import GentMaxwell, gent_denominator
from .membrane import ConeMembrane


class ConfigError(ValueError):
    """A config (or a parameter given in code) is missing, unknown or out of range."""


@dataclass(frozen=True)
class Field:
    """An allowed config field: its range (bounds, open or closed) and its unit."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    unit: str = ""

    def describe(self) -> str:
        left = "(" if self.lo_open else "["
        right = ")" if self.hi_open or math.isinf(self.hi) else "]"
        unit = f" {self.unit}" if self.unit else ""
        return f"{left}{self.lo:g}, {self.hi:g}{right}{unit}"

    def check(self, name: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name} must be a number in {self.describe()}, got {value!r}")
        v = float(value)
        ok = math.isfinite(v)
        ok &= v > self.lo if self.lo_open else v >= self.lo
        ok &= v < self.hi if self.hi_open else v <= self.hi
        if not ok:
            raise ConfigError(f"{name} = {value!r} is outside the allowed range {self.describe()}")
        return v


POS = Field(0.0, math.inf, lo_open=True)

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
}
ACTUATOR_CLASSES: dict[str, type[ConeActuator]] = {
    "scdea_ls": SCDEA_LS,
    "dcdea_rr": DCDEA_RR,
    "dcdea_ls": DCDEA_LS,
}


#: Model families outside the square-wave cones (rotary, mass cone, planar ...): ``model = kind``
#: -> ``"module:function"`` taking the parsed config dict and returning the validated model.
#: Imported lazily so each family stays in its own module; each validates with :class:`Field`
#: and raises :class:`ConfigError` like the cone loader below (a plain ``ValueError`` from a
#: model's own checks is reported as a :class:`ConfigError` too).
EXTERNAL_LOADERS: dict[str, str] = {
    "rotary_dcdea": "jaxdea.actuators.rotary:model_from_config",
    "planar_gu2017": "jaxdea.actuators._viscoelastic_config:planar_from_config",
    "mass_cone_huang2020": "jaxdea.actuators._viscoelastic_config:mass_cone_from_config",
    "mass_cone_nouhi": "jaxdea.actuators._viscoelastic_config:mass_cone_from_config",
}


class Model(eqx.Module):
    """A configured cone DEA: the actuator and its default drive (square-wave voltage, duty)."""

    actuator: ConeActuator
    voltage: Any
    duty: Any
    name: str = eqx.field(static=True, default="")


def _section(table: dict, name: str, fields: dict[str, Field]) -> dict[str, Any]:
    """Validated ``{key: jnp.float64}`` of a flat TOML table."""
    if not isinstance(table, dict):
        raise ConfigError(f"[{name}] must be a table")
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown key(s) in [{name}]: {', '.join(unknown)}; allowed: {', '.join(fields)}"
        )
    missing = [k for k in fields if k not in table]
    if missing:
        wanted = ", ".join(f"{k} (allowed range {fields[k].describe()})" for k in missing)
        raise ConfigError(f"missing key(s) in [{name}]: {wanted}")
    return {k: jnp.asarray(f.check(f"{name}.{k}", table[k]), dtype=jnp.float64)
            for k, f in fields.items()}


def _subtables(table: dict, name: str, sub: tuple[str, ...]) -> tuple[dict, dict]:
    flat = {k: v for k, v in table.items() if not isinstance(v, dict)}
    nested = {k: v for k, v in table.items() if isinstance(v, dict)}
    unknown = sorted(set(nested) - set(sub))
    if unknown:
        raise ConfigError(f"unknown table(s) in [{name}]: {', '.join(unknown)}")
    missing = [k for k in sub if k not in nested]
    if missing:
        raise ConfigError(f"missing table(s): {', '.join(f'[{name}.{k}]' for k in missing)}")
    return flat, nested


def model_from_dict(cfg: dict[str, Any]) -> Model:
    """Build and validate a model from a parsed config dictionary (``model`` picks the family)."""
    kind = cfg.get("model")
    if isinstance(kind, str) and kind in EXTERNAL_LOADERS:
        module, func = EXTERNAL_LOADERS[kind].split(":")
        try:
            return getattr(importlib.import_module(module), func)(cfg)
        except ConfigError:
            raise
        except ValueError as exc:  # a model's own check, e.g. J below the stretch invariant
            raise ConfigError(str(exc)) from None
    allowed = {"model", "membrane", "actuator", "drive"}
    unknown = sorted(set(cfg) - allowed)
    if unknown:
        raise ConfigError(f"unknown top-level key(s): {', '.join(unknown)}; "
                          f"allowed: {', '.join(sorted(allowed))}")
    for key in sorted(allowed):
        if key not in cfg:
            raise ConfigError(f"missing top-level key: {key}")
    kind = cfg["model"]
    if kind not in ACTUATOR_CLASSES:
        kinds = [*ACTUATOR_CLASSES, *EXTERNAL_LOADERS]
        raise ConfigError(f"model = {kind!r} is not one of {', '.join(kinds)}")

    flat, nested = _subtables(cfg["membrane"], "membrane", ("dielectric", "electrode"))
    geo = _section(flat, "membrane", MEMBRANE_FIELDS)
    if not geo["outer_radius"] > geo["inner_radius"]:
        raise ConfigError(
            f"membrane.outer_radius = {float(geo['outer_radius']):g} m must be greater than "
            f"membrane.inner_radius = {float(geo['inner_radius']):g} m (allowed range "
            f"({float(geo['inner_radius']):g}, inf) m)"
        )
    dielectric = GentMaxwell(**_section(nested["dielectric"], "membrane.dielectric",
                                        MATERIAL_FIELDS))
    electrode = GentMaxwell(**_section(nested["electrode"], "membrane.electrode",
                                       MATERIAL_FIELDS))
    membrane = ConeMembrane(**geo, dielectric=dielectric, electrode=electrode)
    act = _section(cfg["actuator"], "actuator", ACTUATOR_FIELDS[kind])
    actuator = ACTUATOR_CLASSES[kind](membrane=membrane, **act)
    drive = _section(cfg["drive"], "drive", DRIVE_FIELDS)
    _check_rest_state(actuator)
    return Model(actuator=actuator, voltage=drive["voltage"], duty=drive["duty"], name=kind)


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


def load_config(path: str | Path) -> Model:
    """Read a TOML config (see ``configs/``) and return the validated :class:`Model`."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            cfg = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    try:
        return model_from_dict(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
