"""The field readers shared by every config loader: one range type, one table reader, one
list reader, one top-level check. Errors name ``section.key`` and the allowed range."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
from jaxtyping import Array

from .._checks import ConfigError


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
        try:
            v = float(value)
        except OverflowError:  # an integer beyond float64 (|value| > 1.8e308)
            v = math.inf
        ok = math.isfinite(v)
        ok &= v > self.lo if self.lo_open else v >= self.lo
        ok &= v < self.hi if self.hi_open else v <= self.hi
        if not ok:
            raise ConfigError(f"{name} = {value!r} is outside the allowed range {self.describe()}")
        return v


#: A strictly positive number.
POS = Field(0.0, math.inf, lo_open=True)


def table_of(value: Any, name: str) -> dict:
    """A copy of the TOML table ``value`` (a dict); ``ConfigError`` naming ``[name]`` if it is
    a number, string, list or anything else."""
    if not isinstance(value, dict):
        raise ConfigError(f"[{name}] must be a table of key = value lines, got {value!r}")
    return dict(value)


def section(table: Any, name: str, fields: dict[str, Field]) -> dict[str, Array]:
    """Validated ``{key: float64 array}`` of a flat TOML table with exactly ``fields``."""
    if not isinstance(table, dict):
        raise ConfigError(f"[{name}] must be a table")
    unknown = sorted(map(str, set(table) - set(fields)))
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


def subtables(table: Any, name: str, sub: tuple[str, ...]) -> tuple[dict, dict]:
    """``table`` split into its plain keys and its sub-tables, which must be exactly ``sub``."""
    if not isinstance(table, dict):
        raise ConfigError(f"[{name}] must be a table")
    flat = {k: v for k, v in table.items() if not isinstance(v, dict)}
    nested = {k: v for k, v in table.items() if isinstance(v, dict)}
    unknown = sorted(map(str, set(nested) - set(sub)))
    if unknown:
        raise ConfigError(f"unknown table(s) in [{name}]: {', '.join(unknown)}")
    missing = [k for k in sub if k not in nested]
    if missing:
        raise ConfigError(f"missing table(s): {', '.join(f'[{name}.{k}]' for k in missing)}")
    return flat, nested


def number_list(table: dict, name: str, key: str, field: Field, n: int | None = None) -> Array:
    """Validated float64 array of the non-empty list ``table[key]`` (``n`` entries if given);
    each entry is checked as ``name.key[i]``."""
    full = f"{name}.{key}"
    if key not in table:
        raise ConfigError(f"missing key {full}: a list, each value in {field.describe()}")
    val = table[key]
    if not isinstance(val, list) or not val:
        raise ConfigError(f"{full} must be a non-empty list of numbers in {field.describe()}, "
                          f"got {val!r}")
    if n is not None and len(val) != n:
        raise ConfigError(f"{full} must have {n} entries, got {len(val)}")
    return jnp.asarray([field.check(f"{full}[{i}]", x) for i, x in enumerate(val)],
                       dtype=jnp.float64)


def check_top(cfg: dict, kind: str, required: tuple[str, ...],
              optional: tuple[str, ...] = ()) -> None:
    """The top level of a config of family ``kind``: exactly ``model``, the ``required``
    tables and any of ``optional``."""
    allowed = {"model", *required, *optional}
    unknown = sorted(map(str, set(cfg) - allowed))
    if unknown:
        raise ConfigError(f"unknown top-level key(s) for model {kind!r}: {', '.join(unknown)}; "
                          f"allowed: {', '.join(sorted(allowed))}")
    for key in required:
        if key not in cfg:
            raise ConfigError(f"missing table [{key}] for model {kind!r}")
