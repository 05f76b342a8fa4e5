"""Fitted configs: a TOML config rewritten in place with fitted values, comments and layout
kept, and checked to parse back to those values."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from .._checks import CalibrationError
from ..provenance import MARK, check_replaceable_file, toml_mark

__all__ = ["config_keys", "fitted_config_text", "write_fitted_config"]


def _cfg_paths(cfg: dict, prefix: tuple = ()) -> list[tuple[str, ...]]:
    out = []
    for k, v in cfg.items():
        if isinstance(v, dict):
            out += _cfg_paths(v, prefix + (k,))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(prefix + (k,))
    return out


def config_keys(cfg: dict, names) -> dict[str, tuple[str, ...]]:
    """The config key of each model parameter: the numeric config entry whose path shares the
    longest dot-suffix with the parameter's path.

    **Arguments:**

    - `cfg`: the parsed config (``tomllib.loads``).
    - `names`: model parameter paths (e.g. ``"actuator.membrane.dielectric.mu_A"``).

    **Returns:**

    ``{name: (table, ..., key)}``; :class:`~jaxdea.CalibrationError` if a name matches no
    key or several equally well.
    """
    keys = _cfg_paths(cfg)
    out = {}
    for name in names:
        parts = tuple(name.split("."))
        best, score = [], 0
        for k in keys:
            n = 0
            while n < min(len(k), len(parts)) and k[-1 - n] == parts[-1 - n]:
                n += 1
            if n > score:
                best, score = [k], n
            elif n == score and n > 0:
                best.append(k)
        if not best:
            raise CalibrationError(f"cannot map the fitted parameter {name} to a key of the "
                                   "config file (no config key has that name)")
        if len(best) > 1:
            raise CalibrationError(f"the fitted parameter {name} matches several config keys: "
                                   + ", ".join(".".join(b) for b in best))
        out[name] = best[0]
    return out


_TABLE = re.compile(r"^\s*\[([^\[\]]+)\]\s*(#.*)?$")
_KEYLINE = re.compile(r"^(\s*)([A-Za-z0-9_\-]+)(\s*=\s*)([^#\s]+)(.*)$")


def fitted_config_text(text: str, updates: dict[tuple[str, ...], float],
                       header: str = "") -> str:
    """A TOML config with some values replaced in place, comments and layout kept.

    **Arguments:**

    - `text`: the config's text.
    - `updates`: ``{(table, ..., key): value}``; each must be a ``key = value`` line under its
      ``[table]`` header (dotted keys and inline tables are not edited).
    - `header`: lines prepended as comments.

    **Returns:**

    The new text; each replaced line is marked ``# fitted``.
    """
    lines = text.splitlines()
    table: tuple[str, ...] = ()
    done = set()
    for i, line in enumerate(lines):
        m = _TABLE.match(line)
        if m:
            table = tuple(p.strip().strip('"') for p in m.group(1).split("."))
            continue
        m = _KEYLINE.match(line)
        if m and table + (m.group(2),) in updates:
            key = table + (m.group(2),)
            lines[i] = (f"{m.group(1)}{m.group(2)}{m.group(3)}{float(updates[key])!r}"
                        f"{m.group(5)}")
            if "fitted" not in m.group(5):
                lines[i] += "  # fitted" if "#" not in m.group(5) else " (fitted)"
            done.add(key)
    missing = [".".join(k) for k in updates if k not in done]
    if missing:
        raise CalibrationError(f"could not find {', '.join(missing)} as 'key = value' lines in "
                               "the config text (dotted keys and inline tables are not edited)")
    head = "".join(f"# {h}\n" for h in header.splitlines()) if header else ""
    return head + "\n".join(lines) + "\n"


def write_fitted_config(config_path, out_path, params: dict[str, float], header: str = ""):
    """Write a config with fitted values, checking that it parses back to those values.

    **Arguments:**

    - `config_path`: the config the fit started from.
    - `out_path`: where to write (parent folders are made).
    - `params`: ``{model parameter path: value}`` (``CalibrationResult.params``).
    - `header`: lines prepended as comments.

    **Returns:**

    ``out_path`` as a :class:`~pathlib.Path`.
    """
    config_path, out_path = Path(config_path), Path(out_path)
    check_replaceable_file(out_path, "out_path", CalibrationError)
    # jaxdea's mark first (jaxdea.provenance), not twice when the start was jaxdea's too
    text = "".join(line for line in config_path.read_text().splitlines(keepends=True)
                   if not line.startswith(f"# {MARK}"))
    cfg = tomllib.loads(text)
    keys = config_keys(cfg, list(params))
    new = fitted_config_text(text, {keys[n]: v for n, v in params.items()}, header)
    back = tomllib.loads(new)
    for n, k in keys.items():
        v = back
        for part in k:
            v = v[part]
        if float(v) != float(params[n]):  # pragma: no cover - guarded by the text edit
            raise CalibrationError(f"writing {'.'.join(k)} failed: read back {v}")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(toml_mark() + new)
    return out_path
