"""The optional ``[payload]`` table of a cone config: the load the actuator drives.

Layout (SI; every key but ``mass`` optional, defaults as in :mod:`jaxdea.payloads`)::

    [payload]          mass (kg), linear (N s/m), quadratic (N s^2/m^2), coulomb (N),
                       coulomb_velocity (m/s)                               -> Drag
    [payload.elastic]  stiffness (N/m), preload (N), anchor (m)             -> + Elastic
    [payload.gravity]  tilt (rad), g (m/s^2)                                -> + Gravity

The studies take it as ``payload=jaxdea.load_payload(path)``; the CLI uses it when no
``--damping`` or payload flag is given.
"""

from __future__ import annotations

import math
from typing import Any

from .._checks import ConfigError
from ..payloads import STANDARD_GRAVITY, Drag, Elastic, Gravity, PayloadLaw
from .fields import POS, Field, section

NONNEG = Field(0.0, math.inf)
ANY = Field()
#: ``{table: {key: (Field with unit, default or None if required)}}``
PAYLOAD_FIELDS: dict[str, dict[str, tuple[Field, float | None]]] = {
    "payload": {
        "mass": (Field(0.0, math.inf, unit="kg"), None),
        "linear": (Field(0.0, math.inf, unit="N s/m"), 0.0),
        "quadratic": (Field(0.0, math.inf, unit="N s^2/m^2"), 0.0),
        "coulomb": (Field(0.0, math.inf, unit="N"), 0.0),
        "coulomb_velocity": (Field(0.0, math.inf, lo_open=True, unit="m/s"), 1e-3),
    },
    "payload.elastic": {
        "stiffness": (Field(0.0, math.inf, unit="N/m"), None),
        "preload": (Field(unit="N"), 0.0),
        "anchor": (Field(unit="m"), None),  # optional: the actuator's rest position
    },
    "payload.gravity": {
        "tilt": (Field(unit="rad"), 0.0),
        "g": (Field(0.0, math.inf, unit="m/s^2"), STANDARD_GRAVITY),
    },
}
_OPTIONAL_NONE = {("payload.elastic", "anchor")}


def _read(table: Any, name: str) -> dict:
    if not isinstance(table, dict):
        raise ConfigError(f"[{name}] must be a table of key = value lines, got {table!r}")
    spec = PAYLOAD_FIELDS[name]
    missing = [k for k, (_, d) in spec.items() if d is None and k not in table
               and (name, k) not in _OPTIONAL_NONE]
    if missing:
        raise ConfigError(f"missing key(s) in [{name}]: " + ", ".join(
            f"{k} (allowed range {spec[k][0].describe()})" for k in missing))
    full = {k: d for k, (_, d) in spec.items() if d is not None}
    full.update(table)
    fields = {k: f for k, (f, _) in spec.items() if k in full}
    return {k: float(v) for k, v in section(full, name, fields).items()}


def payload_from_config(cfg: dict[str, Any]) -> PayloadLaw | None:
    """The payload law of a parsed cone config's ``[payload]`` table (``None`` if it has
    none). Raises :class:`~jaxdea.ConfigError` naming ``payload.key`` and its allowed range."""
    if "payload" not in cfg:
        return None
    table = cfg["payload"]
    if not isinstance(table, dict):
        raise ConfigError(f"[payload] must be a table of key = value lines, got {table!r}")
    nested = {k: v for k, v in table.items() if isinstance(v, dict)}
    unknown = sorted(set(nested) - {"elastic", "gravity"})
    if unknown:
        raise ConfigError(f"unknown table(s) in [payload]: {', '.join(unknown)}; allowed: "
                          "[payload.elastic], [payload.gravity]")
    law: PayloadLaw = Drag(**_read({k: v for k, v in table.items() if k not in nested},
                                   "payload"))
    if "elastic" in nested:
        law = law + Elastic(**_read(nested["elastic"], "payload.elastic"))
    if "gravity" in nested:
        law = law + Gravity(**_read(nested["gravity"], "payload.gravity"))
    return law


__all__ = ["PAYLOAD_FIELDS", "POS", "payload_from_config"]
