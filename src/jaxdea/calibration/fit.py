"""Parameter identification: fit any subset of a model's parameters to measured data.

``calibrate(model, data, fit=[...], bounds={...}, method=...)`` returns a
:class:`CalibrationResult` with the fitted model, the loss history, the papers' error metrics
``e_rms`` / ``e_m`` (paper 001 Sec 4.2, paper 002 eq 26) and a Gauss-Newton curvature /
covariance estimate at the optimum.

Parameters
----------
A parameter is named by its path in the model pytree (``"actuator.membrane.dielectric.mu_A"``)
or by any dot-suffix of that path that is unique (``"dielectric.mu_A"``, ``"tau"`` when only
one ``tau`` exists); :func:`parameter_names` lists them. Unfitted parameters are held.

Transforms
----------
Each fitted parameter ``theta`` lives in a *box space* ``u``: ``u = log(theta)`` (default for
parameters whose starting value is positive: moduli, Gent limits, relaxation times, masses)
or ``u = theta`` (``transforms={name: "linear"}``). Bounds ``(lo, hi)`` are in ``theta``; a
log parameter needs ``lo > 0``. Gradient methods work in an unconstrained ``z``: a finite box
is mapped by ``u = ulo + (uhi - ulo) sigmoid(z)``, a half-open one by a softplus, an open one
by ``u = z``. So moduli and times stay positive and inside their bounds whatever the step.
Differential evolution searches the box ``[ulo, uhi]`` directly (uniform in log for log
parameters, as a search over "several decades" should be).

Methods
-------
- ``"lbfgs"``: scipy's L-BFGS-B (Fortran, Moré-Thuente-type line search) on ``z`` with the
  exact JAX gradient. Chosen over ``optax.lbfgs`` because its line search runs on the host,
  so the model's value-and-gradient is compiled once (the optax zoom line search traces the
  model a second time inside its ``while_loop``) and every model evaluation is counted.
- ``"adam"``: ``optax.adam`` on ``z``.
- ``"lm"``: scipy's ``least_squares`` (trust-region reflective) with the JAX Jacobian: a
  Gauss-Newton method, natural for these least-squares fits.
- ``"de"``: scipy's ``differential_evolution`` with a *vectorized* objective: each generation
  (the whole population) is one ``jax.vmap``-ed, jitted model call. Defaults are paper 001's
  settings: population 240, 115 generations, mutation F = 0.6, crossover CR = 0.9, the
  classic DE/rand/1/bin strategy, Latin-hypercube initial population, no polishing.
  scipy rather than a hand-written DE (or evosax, not a dependency): it is maintained,
  already a dependency, and its ``vectorized=True`` mode hands us the population at once.

Gradients (``jac="auto"``, the default) are forward mode for frequency responses
(``jax.jacfwd`` of the residual vector, one pass with one tangent per parameter: it goes
through the sweep engine's ``lax.while_loop``, which reverse mode cannot) and reverse mode for
time series (``value_and_grad``: diffrax's checkpointed adjoint is a ``custom_vjp``, which
forward mode cannot go through). The residual Jacobian of the curvature estimate and of
``"lm"`` is built the same way (``jacfwd`` or ``jacrev``). ``jac="fwd"``/``"rev"`` force one.

Loss
----
Residuals are per channel (``displacement``, ``force``, ``amplitude``, ``P_out``) and each
channel has the same total weight: ``loss = mean_c mean_i r_ci^2`` with ``r = (model -
data) / range(data)`` (``"mse"``, the normalisation of e_rms), ``r = model / data - 1``
(``"relative"``: right for data spanning decades, e.g. P_out over f) or
``r = log(model / data)`` (``"log"``).

Divergence: a non-finite loss at an accepted iterate (or a loss that stays non-finite) stops
the fit with :class:`CalibrationError`; parameters are never returned as NaN.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError, DataError
from .data import Data, FrequencyResponse, TimeSeries

METHODS = ("lbfgs", "adam", "de", "lm")
LOSSES = ("mse", "relative", "log")
TRANSFORMS = ("log", "linear")

#: Paper 001 (Sec 4.2) differential-evolution settings.
DE_PAPER = dict(popsize=240, maxiter=115, mutation=0.6, recombination=0.9,
                strategy="rand1bin")


# ---- parameters -------------------------------------------------------------------------------


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
    1-D floating-point leaves (e.g. the moduli of a chain of springs): ``{name: value}``."""
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
    """Full paths of ``names`` (full paths or unique dot-suffixes); errors name the problem."""
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
    full = resolve_names(model, names)
    avail = parameter_names(model)
    return {n: avail[n] for n in full}


def set_params(model, values: dict[str, Any]):
    """A copy of ``model`` with the leaves at the given paths (or suffixes) replaced."""
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
    """Validated :class:`Param` list for ``fit`` (errors name the parameter and the problem)."""
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


def _with_theta(model, params: list[Param], theta):
    names, leaves, treedef = _leaves(model)
    leaves = list(leaves)
    for i, p in enumerate(params):
        _put(leaves, p.index, p.elem, theta[i])
    return jax.tree_util.tree_unflatten(treedef, leaves)


# ---- metrics ---------------------------------------------------------------------------------


def error_metrics(measured, predicted) -> tuple[float, float]:
    """Paper 002 eq 26 / paper 001 Sec 4.2: ``(e_rms, e_m)`` in percent.

    ``e_m = max|z_e - z_m| / (max z_m - min z_m) * 100 %`` as printed. ``e_rms`` is printed as
    ``sqrt(mean (z_e - z_m)^2) * 100 %`` with no normaliser, which only makes sense as a
    percentage of a reference; we divide it by the same model range as ``e_m``, so both are
    dimensionless percentages of the model's peak-to-peak output.
    """
    ze = np.asarray(measured, dtype=float).ravel()
    zm = np.asarray(predicted, dtype=float).ravel()
    span = float(np.max(zm) - np.min(zm))
    if not span > 0:
        span = float(np.max(np.abs(zm))) or 1.0
    err = ze - zm
    return (float(np.sqrt(np.mean(err * err)) / span * 100.0),
            float(np.max(np.abs(err)) / span * 100.0))


# ---- predictors ------------------------------------------------------------------------------


def frequency_response(model, data: FrequencyResponse, *, cycles: int = 20, average: int = 5,
                       dt_max: float = 5e-4, points_per_cycle: int | None = None):
    """Differentiable steady-state response of a cone model (``jaxdea.Model``) at the rows of
    ``data``: ``{"amplitude": m, "P_out": W}``.

    Paper 000's protocol (``cycles`` periods from rest, metrics over the last ``average``) on
    a fixed grid of ``points_per_cycle`` :class:`~jaxdea.solver.LawsonRK4` steps per period
    (default: the even count that keeps steps below ``dt_max``; drive edges lie on the grid).
    Fixed steps make the output a smooth function of the parameters, so forward and reverse
    derivatives match finite differences; :func:`jaxdea.sweep`'s adaptive engine gives the
    same numbers to ~0.1-1 % (amplitude is the extremum of the samples, not of the Hermite
    interpolant). All rows run as one ``vmap``.
    """
    from ..solver import LawsonRK4, SemilinearTerm
    from ..studies.loadings import make_loadings

    if not (1 <= average <= cycles):
        raise CalibrationError(f"need 1 <= average <= cycles, got {average}, {cycles}")
    f = np.asarray(data.f, dtype=float)
    if points_per_cycle is None:
        points_per_cycle = int(2 * math.ceil(1.0 / (float(f.min()) * dt_max) / 2.0))
    ppc = max(int(points_per_cycle), 8)
    act = model.actuator
    loadings = make_loadings(model, data.mass, data.damping, f)
    solver = LawsonRK4()
    term = SemilinearTerm(act.vector_field, act.linearisation)
    y0 = act.initial_state()
    start = (cycles - average) * ppc

    def one(loading):
        dt = 1.0 / loading.drive.frequency / ppc

        def step(y, k):
            t0 = k * dt
            y1, *_ = solver.step(term, t0, t0 + dt, y, loading, None, False)
            return y1, (y1.q[act.payload_dof], y1.payload_work)

        _, (x, w) = jax.lax.scan(step, y0, jnp.arange(cycles * ppc, dtype=jnp.float64))
        xw = x[start - 1:] if start > 0 else jnp.concatenate([y0.q[act.payload_dof][None], x])
        w0 = w[start - 1] if start > 0 else y0.payload_work
        return 0.5 * (jnp.max(xw) - jnp.min(xw)), (w[-1] - w0) * loading.drive.frequency / average

    amp, p_out = jax.vmap(one)(loadings)
    return {"amplitude": amp, "P_out": p_out}


def transient_predictor(signal, *, fixed_steps: int | None = None, voltage_tol: float = 0.01,
                        **solve_kwargs) -> Callable:
    """``predict(model, data)`` for the viscoelastic models of :mod:`jaxdea.viscoelastic` (mass
    cone of papers 001/002, planar DEA of 004) under a known drive ``signal`` (e.g. the eq-25
    :class:`~jaxdea.signals.MultiSine`): ``{"displacement": m}`` at ``data.t``.

    The drive's kink times (and the fixed step grid) are computed eagerly, so the predictor
    can run inside the fit's ``jit``/``vmap``. The data's ``voltage`` column must match
    ``signal`` to ``voltage_tol`` of its range (else :class:`DataError`): the model is driven
    by ``signal``, not by the sampled voltage. ``solve_kwargs``: ``rtol``, ``atol``,
    ``max_steps`` of :func:`jaxdea.viscoelastic.solve`.

    Not yet exercised by a recovery test (problem (a) of issue 5 is open).
    """
    from ..studies import transient as ve

    checked: set[int] = set()

    def predict(model, data: TimeSeries):
        if not isinstance(data, TimeSeries):
            raise DataError("transient_predictor needs a TimeSeries (t, voltage, displacement)")
        ts = np.asarray(data.t, dtype=float)
        with jax.ensure_compile_time_eval():
            if id(data) not in checked:
                v = np.asarray(jax.vmap(signal)(jnp.asarray(ts)))
                err = float(np.max(np.abs(v - data.voltage)))
                span = float(np.ptp(data.voltage)) or 1.0
                if err > voltage_tol * span:
                    raise DataError(f"{data.source}: the measured voltage differs from the "
                                    f"drive signal by up to {err:.4g} V ({100 * err / span:.2g} "
                                    "% of its range): give the signal that produced the data")
                checked.add(id(data))
            if fixed_steps is not None:
                grid = jnp.asarray(ve._step_grid(signal, ts, int(fixed_steps)))
            else:
                jump = jnp.asarray(np.asarray(signal.kink_times(ve._cycles(signal, ts[-1]))))
        if fixed_steps is not None:
            kw = dict(rtol=1e-8, atol=1e-10) | solve_kwargs
            out = ve._solve(model, signal, jnp.asarray(ts), None, grid, kw["rtol"], kw["atol"],
                            int(grid.shape[0]) + 1)
            return {"displacement": out[1]["displacement"]}
        return {"displacement": ve.displacement(model, signal, ts, jump_ts=jump,
                                                **solve_kwargs)}

    return predict


#: ``(model class, data class) -> predict``; other model families register here.
PREDICTORS: dict[tuple[type, type], Callable] = {}


def default_predict(model, data) -> Callable:
    """The predictor registered for this model and data kind (see :data:`PREDICTORS`)."""
    from ..models.cone import Model

    if isinstance(data, FrequencyResponse) and isinstance(model, Model):
        return frequency_response
    for (mcls, dcls), fn in PREDICTORS.items():
        if isinstance(model, mcls) and isinstance(data, dcls):
            return fn
    raise CalibrationError(f"no predictor for a {type(model).__name__} model and "
                           f"{type(data).__name__} data: pass predict=f(model, data) -> "
                           "{channel: array}")


# ---- the objective --------------------------------------------------------------------------


class _Objective:
    """Residuals, loss and derivatives of a fit in u (box) and z (unconstrained) space."""

    def __init__(self, model, data, params, predict, loss):
        self.model, self.data, self.params = model, data, params
        channels = data.channels
        self.meas = {k: np.asarray(v, dtype=float) for k, v in channels.items()}
        nc = len(self.meas)
        self.weights, self.scales = {}, {}
        for k, y in self.meas.items():
            if loss == "mse":
                span = float(np.ptp(y)) or float(np.max(np.abs(y))) or 1.0
                self.scales[k] = span
            elif np.any(y == 0) or (loss == "log" and np.any(y <= 0)):
                raise DataError(f"{data.source}: loss={loss!r} needs "
                                f"{'positive' if loss == 'log' else 'non-zero'} data, but "
                                f"channel {k!r} has zeros/negatives; use loss='mse'")
            self.weights[k] = 1.0 / math.sqrt(y.size * nc)
        self.loss_kind = loss
        self.predict = predict
        self.n_resid = sum(y.size for y in self.meas.values())

        def residual_u(u):
            theta = jnp.stack([p.theta_of_u(u[i]) for i, p in enumerate(params)])
            pred = predict(_with_theta(model, params, theta), data)
            parts = []
            for k, y in self.meas.items():
                if k not in pred:
                    raise CalibrationError(f"predict returned no {k!r} channel "
                                           f"(got {', '.join(pred)})")
                p = jnp.ravel(pred[k])
                if loss == "mse":
                    r = (p - y) / self.scales[k]
                elif loss == "relative":
                    r = p / y - 1.0
                else:
                    r = jnp.log(p / y)
                parts.append(r * self.weights[k])
            return jnp.concatenate(parts)

        def u_of_z(z):
            return jnp.stack([p.u_of_z(z[i]) for i, p in enumerate(params)])

        self.residual_u = residual_u
        self.u_of_z = u_of_z
        self.residual_z = lambda z: residual_u(u_of_z(z))
        self._cache: dict[str, Callable] = {}

    # compiled pieces, built on first use
    def fn(self, name: str) -> Callable:
        if name not in self._cache:
            rz = self.residual_z
            if name == "resid_z":
                f = jax.jit(rz)
            elif name == "jac_z":  # (J, r) in one forward pass with one tangent per parameter
                f = jax.jit(jax.jacfwd(lambda z: (rz(z), rz(z)), has_aux=True))
            elif name == "jacrev_z":  # (J, r) by reverse mode, one cotangent per residual
                f = jax.jit(jax.jacrev(lambda z: (rz(z), rz(z)), has_aux=True))
            elif name == "vg_z":
                f = jax.jit(jax.value_and_grad(lambda z: jnp.sum(rz(z) ** 2)))
            elif name == "loss_u_batch":
                f = jax.jit(jax.vmap(lambda u: jnp.sum(self.residual_u(u) ** 2)))
            elif name == "du_dz":
                f = jax.jit(jax.jacfwd(self.u_of_z))
            else:  # pragma: no cover
                raise KeyError(name)
            self._cache[name] = f
        return self._cache[name]

    def prediction_from_residuals(self, r) -> dict[str, np.ndarray]:
        """The model output per channel, recovered from the residual vector (no recompile)."""
        out, i = {}, 0
        for k, y in self.meas.items():
            rk = np.asarray(r[i:i + y.size]) / self.weights[k]
            i += y.size
            if self.loss_kind == "mse":
                out[k] = y + rk * self.scales[k]
            elif self.loss_kind == "relative":
                out[k] = y * (1.0 + rk)
            else:
                out[k] = y * np.exp(rk)
        return out

    def z0(self) -> np.ndarray:
        return np.array([p.z_of_u(float(p.u_of_theta(p.init))) for p in self.params])

    def theta_of_z(self, z) -> np.ndarray:
        u = np.asarray(self.u_of_z(jnp.asarray(z)))
        return np.array([float(p.theta_of_u(u[i])) for i, p in enumerate(self.params)])

    def theta_of_u(self, u) -> np.ndarray:
        return np.array([float(p.theta_of_u(u[i])) for i, p in enumerate(self.params)])

    def jacobian(self, z, jac: str):
        """``(J, r)``: residual Jacobian in z and the residuals, by ``jac`` mode."""
        return self.fn("jac_z" if jac == "fwd" else "jacrev_z")(jnp.asarray(z))

    def value_and_grad(self, z, jac: str):
        z = jnp.asarray(z, dtype=jnp.float64)
        if jac == "fwd":
            J, r = self.fn("jac_z")(z)
            return float(jnp.sum(r * r)), np.asarray(2.0 * (J.T @ r))
        v, g = self.fn("vg_z")(z)
        return float(v), np.asarray(g)


# ---- result ---------------------------------------------------------------------------------


@dataclass
class CalibrationResult:
    """What a fit returns (SI units; ``e_*`` in percent)."""

    model: Any  #: the fitted model (unfitted parameters as given)
    params: dict[str, float]  #: fitted values by full path
    initial: dict[str, float]  #: starting values
    loss: float  #: final loss (see module doc)
    history: list[float]  #: loss after each iteration / generation
    n_evals: int  #: model evaluations (a DE population counts as its size)
    n_grads: int  #: of which with a gradient
    wall_s: float  #: wall time of the optimisation (compilation included)
    method: str
    metrics: dict[str, tuple[float, float]]  #: channel -> (e_rms, e_m), percent
    e_rms: float  #: largest e_rms over channels, percent
    e_m: float  #: largest e_m over channels, percent
    prediction: dict[str, np.ndarray]  #: the fitted model's output per channel
    curvature: np.ndarray | None = None  #: Gauss-Newton Hessian of the loss in u (log) space
    covariance: np.ndarray | None = None  #: parameter covariance in theta (delta method)
    std: dict[str, float] = field(default_factory=dict)  #: 1-sigma of each fitted value
    rel_std: dict[str, float] = field(default_factory=dict)  #: std / |value|
    flat: list[str] = field(default_factory=list)  #: parameters the data do not identify
    message: str = ""
    #: the fit's objective (residuals, compiled derivatives) for inspection and checks
    objective: Any = field(default=None, repr=False)

    def summary(self) -> str:
        lines = [f"method {self.method}: loss {self.loss:.4g}, e_rms {self.e_rms:.3g} %, "
                 f"e_m {self.e_m:.3g} %, {self.n_evals} model evaluations, {self.wall_s:.1f} s"]
        for n, v in self.params.items():
            s = self.rel_std.get(n)
            sd = f" +- {100 * s:.2g} %" if s is not None and math.isfinite(s) else ""
            flat = "  (flat: not identified by the data)" if n in self.flat else ""
            lines.append(f"  {n} = {v:.6g}  (start {self.initial[n]:.6g}){sd}{flat}")
        return "\n".join(lines)


def _curvature(obj: _Objective, z, params, theta, loss, flat_threshold, jac):
    """Gauss-Newton curvature in u, covariance in theta and the flat parameters."""
    J, r = obj.jacobian(z, jac)
    du = np.diag(np.asarray(obj.fn("du_dz")(jnp.asarray(z))))
    Jz = np.asarray(J)
    with np.errstate(divide="ignore", invalid="ignore"):
        Ju = Jz / np.where(du != 0, du, np.nan)[None, :]
    Ju = np.nan_to_num(Ju, nan=0.0)
    H = 2.0 * Ju.T @ Ju
    dof = max(obj.n_resid - len(params), 1)
    s2 = max(float(loss) / dof, 1e-300)
    cov_u = s2 * np.linalg.pinv(0.5 * H, rcond=1e-14, hermitian=True)
    # directions with no curvature at all: infinite variance, not 0 from the pseudo-inverse
    diag_h = np.diag(H)
    scale = np.max(diag_h) if np.max(diag_h) > 0 else 1.0
    dead = diag_h <= 1e-14 * scale
    D = np.array([t if p.log else 1.0 for p, t in zip(params, theta)])
    cov = D[:, None] * cov_u * D[None, :]
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    std[dead] = np.inf
    rel = std / np.maximum(np.abs(theta), 1e-300)
    names = [p.name for p in params]
    flat = [n for n, s in zip(names, rel) if not s <= flat_threshold]
    return H, cov, dict(zip(names, std.tolist())), dict(zip(names, rel.tolist())), flat


def calibrate(model, data: Data, fit, *, bounds=None, method: str = "lbfgs",
              loss: str = "mse", seed: int = 0, predict: Callable | None = None,
              transforms=None, jac: str = "auto", maxiter: int | None = None,
              learning_rate: float = 0.05, tol: float = 1e-10, de_options=None,
              curvature: bool = True, flat_threshold: float = 0.5,
              verbose: bool = False) -> CalibrationResult:
    """Fit the parameters ``fit`` of ``model`` to ``data``.

    ``bounds``: ``{name: (lower, upper)}`` in the parameter's units (needed by ``"de"``);
    ``method``: ``"lbfgs"`` | ``"adam"`` | ``"lm"`` | ``"de"``; ``loss``: ``"mse"`` |
    ``"relative"`` | ``"log"``; ``predict(model, data) -> {channel: array}`` (default from
    :func:`default_predict`); ``transforms``: ``{name: "log" | "linear"}``; ``jac``: ``"auto"``
    (forward mode for frequency responses, reverse mode for time series), ``"fwd"`` or
    ``"rev"``; ``maxiter``: iterations (generations for DE; default 200 / 2000 / 100 / 115
    for lbfgs / adam / lm / de); ``learning_rate``: Adam's step in z; ``de_options``: overrides
    of :data:`DE_PAPER` and of scipy's ``tol``/``atol``/``init``; ``flat_threshold``: a relative
    1-sigma above which a parameter is reported as not identified (``result.flat``).
    """
    if method not in METHODS:
        raise CalibrationError(f"method = {method!r} must be one of {', '.join(METHODS)}")
    if loss not in LOSSES:
        raise CalibrationError(f"loss = {loss!r} must be one of {', '.join(LOSSES)}")
    if jac not in ("auto", "fwd", "rev"):
        raise CalibrationError(f"jac = {jac!r} must be 'auto', 'fwd' or 'rev'")
    if not isinstance(data, (TimeSeries, FrequencyResponse)):
        raise DataError(f"data must be a TimeSeries or FrequencyResponse (jaxdea.load_data), "
                        f"got {type(data).__name__}")
    if jac == "auto":
        jac = "rev" if isinstance(data, TimeSeries) else "fwd"
    params = make_params(model, fit, bounds, transforms)
    if method == "de":
        open_ = [p.name for p in params if not (math.isfinite(p.ulo) and math.isfinite(p.uhi))]
        if open_:
            raise CalibrationError(f"method 'de' searches a box: give finite bounds for "
                                   f"{', '.join(open_)}")
    predict = predict or default_predict(model, data)
    obj = _Objective(model, data, params, predict, loss)
    t0 = time.perf_counter()
    run = {"lbfgs": _run_lbfgs, "adam": _run_adam, "lm": _run_lm, "de": _run_de}[method]
    state = dict(n_evals=0, n_grads=0, history=[])
    z, message = run(obj, state, jac=jac, maxiter=maxiter, lr=learning_rate, tol=tol,
                     seed=seed, de_options=de_options or {}, verbose=verbose)
    wall = time.perf_counter() - t0

    theta = obj.theta_of_z(z) if method != "de" else obj.theta_of_u(z)
    if method == "de":
        z = np.array([p.z_of_u(float(u)) for p, u in zip(params, z)])
    if not np.all(np.isfinite(theta)):
        raise CalibrationError(f"fit ({method}) diverged: non-finite parameters "
                               f"{dict(zip([p.name for p in params], theta.tolist()))}")
    fitted = _with_theta(model, params, jnp.asarray(theta))
    r = np.asarray(obj.fn("resid_z")(jnp.asarray(z)))
    final = float(np.sum(r * r))
    if not math.isfinite(final):
        raise CalibrationError(f"fit ({method}) diverged: the loss at the returned parameters "
                               "is not finite")
    pred = obj.prediction_from_residuals(r)
    metrics = {k: error_metrics(obj.meas[k], pred[k]) for k in obj.meas}
    res = CalibrationResult(
        model=fitted, params={p.name: float(t) for p, t in zip(params, theta)},
        initial={p.name: p.init for p in params}, loss=final, history=state["history"],
        n_evals=state["n_evals"], n_grads=state["n_grads"], wall_s=wall, method=method,
        metrics=metrics, e_rms=max(m[0] for m in metrics.values()),
        e_m=max(m[1] for m in metrics.values()), prediction=pred, message=message,
        objective=obj,
    )
    if curvature:
        (res.curvature, res.covariance, res.std, res.rel_std,
         res.flat) = _curvature(obj, z, params, theta, final, flat_threshold, jac)
    return res


# ---- methods ---------------------------------------------------------------------------------


def _diverged(method: str, k: int, what: str, obj: _Objective, z, hint: str) -> CalibrationError:
    try:
        theta = obj.theta_of_z(z)
        at = ", ".join(f"{p.name} = {t:.4g}" for p, t in zip(obj.params, theta))
    except Exception:  # noqa: BLE001
        at = "unknown"
    return CalibrationError(f"fit diverged ({method}, evaluation {k}): {what} at {at}; {hint}")


def _run_lbfgs(obj: _Objective, state, *, jac, maxiter, tol, verbose, **_):
    from scipy.optimize import minimize

    maxiter = maxiter or 200
    z0 = obj.z0()
    f0, g0 = obj.value_and_grad(z0, jac)
    state["n_evals"] += 1
    state["n_grads"] += 1
    if not (math.isfinite(f0) and np.all(np.isfinite(g0))):
        raise _diverged("lbfgs", 1, f"loss = {f0} / non-finite gradient at the start", obj, z0,
                        "check the start values and the data")
    state["history"].append(f0)
    # scipy sees the loss relative to the start: its ftol (absolute below 1) is then relative
    scale = abs(f0) if f0 != 0 else 1.0
    penalty = 1e6
    bad = {"run": 0, "last_g": g0 / scale}

    def fg(z):
        f, g = obj.value_and_grad(z, jac)
        state["n_evals"] += 1
        state["n_grads"] += 1
        if not (math.isfinite(f) and np.all(np.isfinite(g))):
            bad["run"] += 1
            if bad["run"] >= 20:
                raise _diverged("lbfgs", state["n_evals"], f"loss = {f} on 20 evaluations in "
                                "a row", obj, z, "tighten the bounds")
            return penalty, -bad["last_g"]  # a wall: the line search backs off
        bad["run"], bad["last_g"] = 0, g / scale
        return f / scale, g / scale

    def cb(intermediate_result):
        state["history"].append(float(intermediate_result.fun) * scale)
        if verbose:
            print(f"lbfgs it {len(state['history']) - 1}: loss {state['history'][-1]:.6g}")

    res = minimize(fg, z0, jac=True, method="L-BFGS-B", callback=cb,
                   options=dict(maxiter=maxiter, maxfun=10 * maxiter, ftol=tol, gtol=1e-14,
                                maxcor=20))
    if not res.fun < penalty:
        raise _diverged("lbfgs", state["n_evals"], "no finite loss after the start", obj,
                        res.x, "tighten the bounds")
    return res.x, str(res.message)


def _run_adam(obj: _Objective, state, *, jac, maxiter, lr, tol, verbose, **_):
    import optax

    maxiter = maxiter or 2000
    opt = optax.adam(lr)
    z = jnp.asarray(obj.z0())
    st = opt.init(z)
    best = (math.inf, np.asarray(z))
    stall = 0
    for k in range(maxiter):
        f, g = obj.value_and_grad(z, jac)
        state["n_evals"] += 1
        state["n_grads"] += 1
        if not (math.isfinite(f) and np.all(np.isfinite(g))):
            raise _diverged("adam", state["n_evals"], f"loss = {f}", obj, z,
                            f"lower learning_rate (now {lr:g}) or tighten the bounds")
        state["history"].append(f)
        if f < best[0] * (1 - tol):
            stall = 0
        else:
            stall += 1
        if f < best[0]:
            best = (f, np.asarray(z))
        if stall >= 100:
            break
        if verbose and k % 50 == 0:
            print(f"adam step {k}: loss {f:.6g}")
        upd, st = opt.update(jnp.asarray(g), st, z)
        z = optax.apply_updates(z, upd)
    return best[1], f"adam: {len(state['history'])} steps, best loss {best[0]:.4g}"


def _run_lm(obj: _Objective, state, *, jac, maxiter, tol, **_):
    from scipy.optimize import least_squares

    maxiter = maxiter or 100
    cache = {}
    bad = {"run": 0}

    def both(z):
        key = np.asarray(z).tobytes()
        if key not in cache:
            J, r = obj.jacobian(z, jac)
            state["n_evals"] += 1
            state["n_grads"] += 1
            r, J = np.asarray(r), np.asarray(J)
            if np.all(np.isfinite(r)) and np.all(np.isfinite(J)):
                bad["run"] = 0
            else:  # trust-region reflective shrinks its radius on a non-finite trial
                bad["run"] += 1
                if bad["run"] >= 20:
                    raise _diverged("lm", state["n_evals"], "non-finite residuals on 20 "
                                    "evaluations in a row", obj, z, "tighten the bounds")
                J = np.nan_to_num(J)
            cache.clear()
            cache[key] = (r, J)
            state["history"].append(float(r @ r))
        return cache[key]

    res = least_squares(lambda z: both(z)[0], obj.z0(), jac=lambda z: both(z)[1],
                        method="trf", x_scale="jac", max_nfev=maxiter,
                        ftol=max(tol, 1e-15), xtol=1e-12, gtol=1e-15)
    if not np.all(np.isfinite(res.fun)):
        raise _diverged("lm", state["n_evals"], "non-finite residuals at the end", obj, res.x,
                        "tighten the bounds")
    return res.x, str(res.message)


def _run_de(obj: _Objective, state, *, maxiter, seed, de_options, verbose, **_):
    from scipy.optimize import differential_evolution
    from scipy.stats import qmc

    o = dict(DE_PAPER)
    o.update(tol=0.0, atol=0.0)
    unknown = sorted(set(de_options) - set(o) - {"init"})
    if unknown:
        raise CalibrationError(f"unknown de_options {', '.join(unknown)}; allowed: "
                               f"{', '.join([*o, 'init'])}")
    o.update(de_options)
    if maxiter is not None:
        o["maxiter"] = maxiter
    lo = np.array([p.ulo for p in obj.params])
    hi = np.array([p.uhi for p in obj.params])
    n = len(obj.params)
    pop = int(o.pop("popsize"))
    if pop < 5:
        raise CalibrationError(f"DE population {pop} too small: need >= 5")
    init = o.pop("init", None)
    if init is None:
        init = qmc.scale(qmc.LatinHypercube(d=n, rng=np.random.default_rng(seed)).random(pop),
                         lo, hi)
    batch = obj.fn("loss_u_batch")

    def f(x):  # x: (n, S) -> (S,)
        vals = np.asarray(batch(jnp.asarray(x.T)))
        state["n_evals"] += x.shape[1]
        return np.where(np.isfinite(vals), vals, np.inf)

    def cb(intermediate_result):
        state["history"].append(float(intermediate_result.fun))
        if verbose:
            print(f"de generation {len(state['history'])}: best loss "
                  f"{intermediate_result.fun:.6g}")

    res = differential_evolution(
        f, list(zip(lo, hi)), init=init, vectorized=True, updating="deferred",
        polish=False, rng=np.random.default_rng(seed), callback=cb, **o)
    if not np.isfinite(res.fun):
        raise CalibrationError("fit diverged (de): no member of the population had a finite "
                               "loss; check bounds and data")
    return res.x, str(res.message)


# ---- fitted configs ---------------------------------------------------------------------------


def _cfg_paths(cfg: dict, prefix: tuple = ()) -> list[tuple[str, ...]]:
    out = []
    for k, v in cfg.items():
        if isinstance(v, dict):
            out += _cfg_paths(v, prefix + (k,))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(prefix + (k,))
    return out


def config_keys(cfg: dict, names) -> dict[str, tuple[str, ...]]:
    """Config key path (tables..., key) of each model parameter path: the numeric config entry
    whose path shares the longest dot-suffix with the parameter's path (unique, else error)."""
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
    """``text`` (a TOML config) with the values at ``updates`` replaced in place, comments and
    layout kept; ``header`` lines are prepended as comments."""
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
    """Write ``config_path`` with the fitted ``params`` (model paths) to ``out_path``; checks
    that the written file parses back to those values. Returns the output path."""
    import tomllib
    from pathlib import Path

    config_path, out_path = Path(config_path), Path(out_path)
    text = config_path.read_text()
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
    out_path.write_text(new)
    return out_path


# ---- figure -----------------------------------------------------------------------------------


_PLOT_UNITS = {"amplitude": (1e3, "mm"), "P_out": (1e3, "mW"), "displacement": (1e3, "mm"),
               "force": (1.0, "N")}


def plot_fit(result: CalibrationResult, data: Data, path=None):
    """Measured (markers) against the fitted model (lines) for every channel, with the
    residuals underneath; one colour per payload for frequency responses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chans = list(result.prediction)
    fig, axes = plt.subplots(2, len(chans), figsize=(5.2 * len(chans), 5.6), squeeze=False,
                             sharex="col", gridspec_kw={"height_ratios": [3, 1]})
    for j, ch in enumerate(chans):
        k, unit = _PLOT_UNITS.get(ch, (1.0, ""))
        y, p = np.asarray(data.channels[ch]), np.asarray(result.prediction[ch]).ravel()
        ax, axr = axes[0, j], axes[1, j]
        if isinstance(data, FrequencyResponse):
            for gi, ((m, c), idx) in enumerate(data.groups().items()):
                col = f"C{gi}"
                ax.plot(data.f[idx], k * y[idx], "o", ms=4, color=col,
                        label=f"data M = {1e3 * m:g} g, c = {c:g} N s/m")
                ax.plot(data.f[idx], k * p[idx], "-", color=col)
                axr.plot(data.f[idx], k * (y[idx] - p[idx]), ".", color=col)
            axr.set_xlabel("frequency (Hz)")
        else:
            ax.plot(data.t, k * y, ".", ms=2, color="0.4", label="data")
            ax.plot(data.t, k * p, "-", color="C3", lw=1, label="model")
            axr.plot(data.t, k * (y - p), "-", color="C0", lw=0.7)
            axr.set_xlabel("time (s)")
        e_rms, e_m = result.metrics[ch]
        ax.set_title(f"{ch}: e_rms {e_rms:.2f} %, e_m {e_m:.2f} %", fontsize=10)
        ax.set_ylabel(f"{ch} ({unit})")
        axr.set_ylabel(f"data - model ({unit})")
        ax.legend(fontsize=7)
        for a in (ax, axr):
            a.grid(alpha=0.3)
    fig.suptitle(f"calibration ({result.method}): loss {result.loss:.3g}", fontsize=10)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return fig
