"""Parameter paths of a model pytree, and the fitted parameters' transforms and bounds.

A parameter is named by its path in the model pytree (``"actuator.membrane.dielectric.mu_A"``),
``path[i]`` for an element of a 1-D leaf, or by any dot-suffix of that path that is unique
(``"dielectric.mu_A"``, ``"tau"`` when only one ``tau`` exists); :func:`parameter_names` lists
them. A fitted parameter is a :class:`Param`: its leaf, its transform ``theta -> u`` (log or
linear) and its bounds, with the map ``z -> u`` from the unconstrained space of gradient
methods into the box (see :mod:`jaxdea.calibration.fit`; the design study uses the same paths).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import CalibrationError

__all__ = ["TRANSFORMS", "Param", "get_params", "make_params", "parameter_names",
           "resolve_names", "set_params", "with_theta"]

TRANSFORMS = ("log", "linear")


def _path_name(path) -> str:
    parts = []
    for k in path:
        if isinstance(k, jax.tree_util.GetAttrKey):
            parts.append(k.name)
        elif isinstance(k, jax.tree_util.DictKey):
            parts.append(str(k.key))
        elif isinstance(k, jax.tree_util.SequenceKey):
            parts.append(str(k.idx))
        else:
            parts.append(str(k))
    return ".".join(parts)


def _leaves(model) -> tuple[list[str], list[Any], Any]:
    flat, treedef = jax.tree_util.tree_flatten_with_path(model)
    return [_path_name(p) for p, _ in flat], [v for _, v in flat], treedef


def parameter_names(model) -> dict[str, float]:
    """Every scalar floating-point leaf of ``model``, and every element ``path[i]`` of its
    1-D floating-point leaves (e.g. the moduli of a chain of springs).

    **Arguments:**

    - `model`: the model pytree.

    **Returns:**

    ``{full path: value}``, in pytree order.
    """
    names, values, _ = _leaves(model)
    out = {}
    for n, v in zip(names, values):
        if isinstance(v, (float, int)) and not isinstance(v, bool):
            out[n] = float(v)
        elif hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.floating):
            if np.ndim(v) == 0:
                out[n] = float(v)
            elif np.ndim(v) == 1:
                for i, x in enumerate(np.asarray(v)):
                    out[f"{n}[{i}]"] = float(x)
    return out


def _split(name: str) -> tuple[str, int]:
    """``"a.b[2]"`` -> ``("a.b", 2)``; ``"a.b"`` -> ``("a.b", -1)``."""
    if name.endswith("]") and "[" in name:
        base, _, idx = name[:-1].rpartition("[")
        return base, int(idx)
    return name, -1


def _put(leaves: list, index: int, elem: int, value) -> None:
    old = leaves[index]
    dtype = getattr(old, "dtype", jnp.float64)
    if elem < 0:
        leaves[index] = jnp.asarray(value, dtype=dtype)
    else:
        leaves[index] = jnp.asarray(old, dtype=dtype).at[elem].set(value)


def resolve_names(model, names) -> list[str]:
    """Full paths of ``names`` (full paths, unique dot-suffixes or the model's
    ``parameter_aliases``).

    **Arguments:**

    - `model`: the model pytree.
    - `names`: parameter names, as a sequence or one comma-separated string.

    **Returns:**

    The full paths, in the order given.

    **Raises:**

    :class:`~jaxdea.CalibrationError` naming the problem: empty, unknown, ambiguous or
    repeated names.
    """
    if isinstance(names, str):
        names = [n for n in names.split(",") if n.strip()]
    names = [n.strip() for n in names]
    if not names:
        raise CalibrationError("fit is empty: name at least one parameter to fit")
    available = parameter_names(model)
    aliases = getattr(model, "parameter_aliases", {}) or {}
    out = []
    for n in names:
        n2 = aliases.get(n, n)
        if n2 in available:
            full = n2
        else:
            hits = [p for p in available if p.endswith("." + n2)]
            if len(hits) == 1:
                full = hits[0]
            elif len(hits) > 1:
                raise CalibrationError(f"parameter name {n!r} is ambiguous: it matches "
                                       f"{', '.join(hits)}; give more of the path")
            else:
                short = sorted({p.split(".")[-1] for p in available})
                raise CalibrationError(f"unknown parameter {n!r}; the model's scalar "
                                       f"parameters are: {', '.join(short)} (full paths via "
                                       "jaxdea.parameter_names(model))")
        if full in out:
            raise CalibrationError(f"parameter {n!r} ({full}) is listed twice in fit")
        out.append(full)
    return out


def get_params(model, names) -> dict[str, float]:
    """The current values of some parameters.

    **Arguments:**

    - `model`: the model pytree.
    - `names`: parameter names (see :func:`resolve_names`).

    **Returns:**

    ``{full path: value}`` in the order of ``names``.
    """
    full = resolve_names(model, names)
    avail = parameter_names(model)
    return {n: avail[n] for n in full}


def set_params(model, values: dict[str, Any]):
    """A copy of ``model`` with some parameters replaced.

    **Arguments:**

    - `model`: the model pytree.
    - `values`: ``{name: value}``, names as in :func:`resolve_names`.

    **Returns:**

    The model with the leaves (or elements of 1-D leaves) at those paths replaced.
    """
    full = resolve_names(model, list(values))
    names, leaves, treedef = _leaves(model)
    index = {n: i for i, n in enumerate(names)}
    leaves = list(leaves)
    for f, v in zip(full, values.values()):
        base, elem = _split(f)
        _put(leaves, index[base], elem, v)
    return jax.tree_util.tree_unflatten(treedef, leaves)


@dataclass(frozen=True)
class Param:
    """One fitted parameter: its path, leaf index, transform and bounds (in theta)."""

    name: str
    index: int
    init: float
    log: bool
    lo: float
    hi: float
    elem: int = -1  #: element of a 1-D leaf, -1 for a scalar leaf

    @property
    def ulo(self) -> float:
        return math.log(self.lo) if self.log and self.lo > 0 else (
            -math.inf if self.log else self.lo)

    @property
    def uhi(self) -> float:
        return math.log(self.hi) if self.log and math.isfinite(self.hi) else self.hi

    def u_of_theta(self, theta):
        return jnp.log(theta) if self.log else theta

    def theta_of_u(self, u):
        return jnp.exp(u) if self.log else u

    def u_of_z(self, z):
        lo, hi = self.ulo, self.uhi
        if math.isfinite(lo) and math.isfinite(hi):
            return lo + (hi - lo) * jax.nn.sigmoid(z)
        if math.isfinite(lo):
            return lo + jax.nn.softplus(z)
        if math.isfinite(hi):
            return hi - jax.nn.softplus(z)
        return z

    def z_of_u(self, u: float) -> float:
        lo, hi = self.ulo, self.uhi
        if math.isfinite(lo) and math.isfinite(hi):
            s = min(max((u - lo) / (hi - lo), 1e-12), 1 - 1e-12)
            return math.log(s / (1 - s))
        if math.isfinite(lo) or math.isfinite(hi):
            x = max(u - lo if math.isfinite(lo) else hi - u, 1e-300)
            return x + math.log(-math.expm1(-x)) if x < 30 else x  # softplus inverse
        return u


def make_params(model, fit, bounds=None, transforms=None) -> list[Param]:
    """The fitted parameters, validated.

    **Arguments:**

    - `model`: the model pytree; its values are the start values.
    - `fit`: the names of the parameters to fit (see :func:`resolve_names`).
    - `bounds`: ``{name: (lower, upper)}`` in the parameter's units; default unbounded (a log
      parameter is kept positive).
    - `transforms`: ``{name: "log" | "linear"}``; default log for a positive start value,
      else linear.

    **Returns:**

    A list of :class:`Param`, in the order of ``fit``.

    **Raises:**

    :class:`~jaxdea.CalibrationError` naming the parameter and the problem (bounds or
    transform for a parameter not fitted, bad bounds, a start value outside them, ...).
    """
    full = resolve_names(model, fit)
    bounds = dict(bounds or {})
    transforms = dict(transforms or {})
    bfull = dict(zip(resolve_names(model, list(bounds)), bounds.values())) if bounds else {}
    tfull = dict(zip(resolve_names(model, list(transforms)), transforms.values())) \
        if transforms else {}
    for what, d in (("bounds", bfull), ("transforms", tfull)):
        extra = sorted(set(d) - set(full))
        if extra:
            raise CalibrationError(f"{what} given for {', '.join(extra)}, which is not in fit")
    names, leaves, _ = _leaves(model)
    index = {n: i for i, n in enumerate(names)}
    init = parameter_names(model)
    out = []
    for n in full:
        v = init[n]
        kind = tfull.get(n, "log" if v > 0 else "linear")
        if kind not in TRANSFORMS:
            raise CalibrationError(f"transform for {n} is {kind!r}; allowed: log, linear")
        lo, hi = -math.inf, math.inf
        if n in bfull:
            b = bfull[n]
            try:
                lo, hi = (float(x) for x in b)
            except (TypeError, ValueError):
                raise CalibrationError(f"bounds for {n} must be a pair (lower, upper), "
                                       f"got {b!r}") from None
            if math.isnan(lo) or math.isnan(hi):
                raise CalibrationError(f"bounds for {n} contain NaN: ({lo}, {hi})")
            if not lo < hi:
                raise CalibrationError(f"impossible bounds for {n}: lower {lo:g} >= upper "
                                       f"{hi:g}")
        if kind == "log":
            if v <= 0:
                raise CalibrationError(f"{n} = {v:g} cannot be a log-parameter (its value must "
                                       "be > 0); use transforms={name: 'linear'}")
            if n in bfull and lo <= 0:
                raise CalibrationError(f"non-positive lower bound {lo:g} for the log-parameter "
                                       f"{n}: a log-parameter needs lower > 0 (e.g. "
                                       f"{v / 1e3:g}), or use transforms={{'{n}': 'linear'}}")
            lo = max(lo, 0.0)
        if not lo <= v <= hi:
            raise CalibrationError(f"the start value {n} = {v:g} is outside its bounds "
                                   f"[{lo:g}, {hi:g}]")
        base, elem = _split(n)
        out.append(Param(n, index[base], v, kind == "log", lo, hi, elem))
    return out


def with_theta(model, params: list[Param], theta):
    """A copy of ``model`` with the fitted parameters set to ``theta``.

    **Arguments:**

    - `model`: the model pytree.
    - `params`: the fitted parameters (from :func:`make_params`).
    - `theta`: their values, one per parameter, in the parameter's units (may be traced).

    **Returns:**

    The model with those leaves (or elements of 1-D leaves) replaced; everything else held.
    """
    names, leaves, treedef = _leaves(model)
    leaves = list(leaves)
    for i, p in enumerate(params):
        _put(leaves, p.index, p.elem, theta[i])
    return jax.tree_util.tree_unflatten(treedef, leaves)
