"""TOML configs -> validated model objects.

Every field is checked before any computation: an unknown key, a missing key, a non-finite
value or a value outside its allowed range raises :class:`ConfigError` naming the field
(``section.key``) and the allowed range. Values are SI units.

``model = "<kind>"`` picks the family's loader from :data:`LOADERS`, a plain registry of
functions (one module per family in this package). A new family is one loader module and one
line here.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .._checks import ConfigError
from .cones import ACTUATOR_CLASSES, cone_from_config, parameter_range
from .fields import POS, Field
from .payload import payload_from_config
from .rotary import rotary_from_config
from .viscoelastic import mass_cone_from_config, planar_from_config

#: ``model = kind`` -> loader taking the parsed config dict and returning the validated model.
#: Each loader validates with :class:`Field` and raises :class:`ConfigError`; a plain
#: ``ValueError`` from a model's own checks is reported as a :class:`ConfigError` too.
LOADERS: dict[str, Callable[[dict[str, Any]], Any]] = {
    **{kind: cone_from_config for kind in ACTUATOR_CLASSES},
    "rotary_dcdea": rotary_from_config,
    "planar_gu2017": planar_from_config,
    "mass_cone_huang2020": mass_cone_from_config,
    "mass_cone_nouhi": mass_cone_from_config,
}

__all__ = ["LOADERS", "POS", "ConfigError", "Field", "load_config", "load_payload",
           "model_from_dict", "parameter_range", "payload_from_config"]


def model_from_dict(cfg: dict[str, Any]) -> Any:
    """Build and validate a model from a parsed config dictionary (``model`` picks the family).

    Arguments:
        cfg: the parsed TOML document (``tomllib.load``), SI units.

    Returns:
        The validated model: a :class:`jaxdea.Model` for the square-wave cones, the family's
        own model class otherwise.
    """
    if not isinstance(cfg, dict):
        raise ConfigError("a config must be a table of keys (a dict)")
    kind = cfg.get("model")
    if "model" not in cfg:
        raise ConfigError("missing top-level key: model")
    if not isinstance(kind, str) or kind not in LOADERS:
        raise ConfigError(f"model = {kind!r} is not one of {', '.join(LOADERS)}")
    try:
        return LOADERS[kind](cfg)
    except ConfigError:
        raise
    except ValueError as exc:  # a model's own check, e.g. J below the stretch invariant
        raise ConfigError(str(exc)) from None


def load_config(path: str | Path) -> Any:
    """Read a TOML config (see ``configs/``) and return the validated model.

    Arguments:
        path: the ``.toml`` file.

    Returns:
        The validated model (:func:`model_from_dict`).
    """
    path, cfg = _read_toml(path)
    try:
        return model_from_dict(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def load_payload(path: str | Path):
    """Read the payload law of a cone config's optional ``[payload]`` table.

    Arguments:
        path: the ``.toml`` file.

    Returns:
        A payload law (:class:`jaxdea.Drag`, plus :class:`jaxdea.Elastic` and
        :class:`jaxdea.Gravity` with ``[payload.elastic]`` / ``[payload.gravity]``), or
        ``None`` when the config has no ``[payload]`` table.
    """
    path, cfg = _read_toml(path)
    try:
        return payload_from_config(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _read_toml(path: str | Path) -> tuple[Path, dict]:
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(f"a config is a path to a .toml file, got {path!r}")
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return path, tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a directory, not a config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
