"""The project's error types and the argument checks shared by every wing.

Every user-facing check raises one of the errors below, subclasses of :class:`JaxdeaError`
(itself a ``ValueError``), with one line naming the field and its allowed range, before any
computation. The CLI turns each of them into that one line and a non-zero exit code.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np


class JaxdeaError(ValueError):
    """Base of every error jaxdea raises for a user's input."""


class ConfigError(JaxdeaError):
    """A config (or a parameter given in code) is missing, unknown or out of range."""


class SweepError(JaxdeaError):
    """Bad study arguments (sweep, power map, simulation; checked before any computation)."""


class FieldWarning(UserWarning):
    """A study drives the membrane above its dielectric breakdown field (nominal field =
    voltage / thickness at rest): the model computes on, a real film would break down."""


class DataError(JaxdeaError):
    """A measured-data file or array is malformed, incomplete or has bad units."""


class CalibrationError(JaxdeaError):
    """Bad calibration arguments, or a fit that cannot proceed (named parameter, reason)."""


def finite_array(name: str, value: Any, *, positive: bool = False,
                 nonnegative: bool = False, error: type[JaxdeaError] = SweepError) -> np.ndarray:
    """``value`` as a non-empty, finite float array (at least 1-D), optionally ``> 0`` or
    ``>= 0``; raises ``error`` naming ``name`` and the allowed range otherwise."""
    try:  # numbers only: a string (even "1e-3") or a bool is not a value of `name`
        raw = np.asarray(value)
        ok = raw.dtype.kind in "iuf"
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise error(f"{name} must be a number or an array of numbers, got {value!r}")
    arr = np.atleast_1d(raw.astype(float))
    if arr.size == 0:
        raise error(f"{name} is empty: give at least one value")
    if not np.all(np.isfinite(arr)):
        raise error(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise error(f"{name} must be > 0 (allowed range (0, inf)), got min {arr.min():g}")
    if nonnegative and np.any(arr < 0):
        raise error(f"{name} must be >= 0 (allowed range [0, inf)), got min {arr.min():g}")
    return arr


def check_choice(name: str, value: Any, choices: Iterable[str],
                 error: type[JaxdeaError] = SweepError) -> str:
    """``value`` if it is one of ``choices``; else ``error`` listing them."""
    choices = tuple(choices)
    if value not in choices:
        raise error(f"{name} = {value!r} must be one of {', '.join(choices)}")
    return value


def check_int(name: str, value: Any, lo: int = 1, error: type[JaxdeaError] = SweepError) -> int:
    """``value`` if it is an integer (not a bool) ``>= lo``; else ``error``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise error(f"{name} must be an integer >= {lo}, got {value!r}")
    return int(value)


def check_unit_interval(name: str, value: Any, error: type[JaxdeaError] = SweepError) -> float:
    """``value`` if it is a finite real number in the open interval (0, 1) (tolerances)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
            or not (math.isfinite(value) and 0 < value < 1):
        raise error(f"{name} = {value!r} is outside the allowed range (0, 1)")
    return float(value)


def check_protocol(cycles: Any, average: Any) -> None:
    """``cycles`` and ``average``: integers with ``1 <= average <= cycles``."""
    for name, v in (("cycles", cycles), ("average", average)):
        check_int(name, v, 1)
    if average > cycles:
        raise SweepError(f"average = {average} must be <= cycles = {cycles}")


def check_early_exit(early_exit: Any) -> None:
    """``None`` (run every cycle) or a tolerance in (0, 1)."""
    if early_exit is None:
        return
    if isinstance(early_exit, bool) or not isinstance(early_exit, (int, float, np.floating)) \
            or not (math.isfinite(early_exit) and 0 < early_exit < 1):
        raise SweepError(f"early_exit = {early_exit!r} must be None (run every cycle) or a "
                         "tolerance in the allowed range (0, 1)")
