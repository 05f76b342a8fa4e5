"""Bounded multi-start design optimisation of steady-state power (:func:`optimise`).

All starts run in lockstep: every iteration evaluates the objective and its implicit
gradient (:mod:`jaxdea.studies.design`) of every start in one batched call, then takes a
projected-gradient ascent step per start in the unit box of the bounds (Barzilai-Borwein
step length, halved on a decrease, a failed orbit or a step that would exceed the field
limit). The nominal field ``voltage / H_m`` at the zero-voltage static equilibrium
(:func:`nominal_field`) must stay <= ``max_field``; no returned design violates it, and
every returned design has a converged orbit without lock-up or pull-in (status 0).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import JaxdeaError, SweepError, check_int
from ..config.cones import ACTUATOR_FIELDS, DRIVE_FIELDS, MATERIAL_FIELDS, MEMBRANE_FIELDS
from ..engine.sensitivity import Steady, solve_designs
from ..models.cone import Model
from ..params import get_params, set_params
from ..provenance import check_replaceable_file, toml_mark
from .builder import LAW, check_values, law_value, make_builder, resolve, split_names
from .design import DESIGN_STEADY, check_band, peak_designs
from .loadings import check_cone_model, nominal_field

OBJECTIVES = ("pmax", "power", "efficiency")


@dataclass
class OptimiseResult:
    """What :func:`optimise` returns (SI units)."""

    model: Model  #: the optimised model
    values: dict  #: the varied parameters at the optimum
    objective: float  #: objective there (W for power objectives)
    f_at_P_max: float | None  #: peak frequency (objective "pmax"), Hz
    gradient: dict  #: d objective / d parameter at the optimum
    active: list  #: the active bounds and constraints, in words
    field: float  #: nominal field at the optimum, V/m
    start_objective: float  #: objective of the first start (the given design if in bounds)
    history: list = field(default_factory=list)  #: per iteration: the starts' objectives
    path: list = field(default_factory=list)  #: per iteration: the starts' values (starts, n)
    #: P_out, P_in (W), efficiency, amplitude (m) of the returned design's orbit (at
    #: ``f_at_P_max`` for "pmax"; empty for a callable objective)
    metrics: dict = field(default_factory=dict)
    #: why the returned start stopped: "gradient" (projected gradient below ``gtol``),
    #: "step" (step length below 1e-7 of the box), or "maxiter" (the iteration limit: not a
    #: converged optimum)
    stopped: str = "maxiter"

    @property
    def converged(self) -> bool:
        """Whether the returned start stopped by a convergence test, not the iteration limit."""
        return self.stopped in ("gradient", "step")

    def to_toml(self, path) -> Path:
        """Write the optimised model as a config that :func:`jaxdea.load_config` reads.

        **Arguments:**

        - `path`: the file to write (parent folders are made).

        **Returns:**

        The path.
        """
        return write_cone_toml(self.model, path, header=f"optimised: {self.values}")


def write_cone_toml(model: Model, path, header: str = "") -> Path:
    """A cone config (``configs/*.toml`` layout) with the values of ``model``.

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model` (with its ``name``).
    - `path`: where to write.
    - `header`: a comment line at the top.

    **Returns:**

    The path.
    """
    act, mem = model.actuator, model.actuator.membrane
    fmt = lambda obj, names: "".join(  # noqa: E731
        f"{k} = {float(getattr(obj, k))!r}\n" for k in names)
    text = toml_mark() + (f"# {header}\n" if header else "")  # jaxdea.provenance
    text += f'model = "{act.name}"\n\n[membrane]\n'
    text += fmt(mem, MEMBRANE_FIELDS)
    for part in ("dielectric", "electrode"):
        text += f"\n[membrane.{part}]\n" + fmt(getattr(mem, part), MATERIAL_FIELDS)
    text += "\n[drive]\n" + fmt(model, DRIVE_FIELDS)
    text += "\n[actuator]\n" + fmt(act, ACTUATOR_FIELDS[act.name])
    path = Path(path)
    check_replaceable_file(path, "path", SweepError)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _check_inputs(model, vary, objective, band, freq, starts, max_field, x0, payload=None):
    check_cone_model(model)
    if not isinstance(vary, dict) or not vary:
        raise SweepError("vary must be a non-empty dict {name: (lower, upper)}")
    mapping = resolve(model, list(vary), payload)
    if any(v == "freq" for v in mapping.values()):
        raise SweepError("freq cannot be varied: give freq= or band=")
    bounds = {}
    for k, b in vary.items():
        try:
            lo, hi = (float(x) for x in b)
        except (TypeError, ValueError):
            raise SweepError(f"vary[{k!r}] must be a pair (lower, upper), got {b!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise SweepError(f"vary[{k!r}] = ({lo}, {hi}) must be finite (allowed range: "
                             "finite lower < upper)")
        if not lo < hi:
            raise SweepError(f"vary[{k!r}] = ({lo:g}, {hi:g}): lower must be < upper")
        bounds[k] = (lo, hi)
    check_values(model, mapping, bounds, "vary")  # both bounds inside the parameter's range
    if not (isinstance(objective, str) and objective in OBJECTIVES) and not callable(objective):
        raise SweepError(f"objective = {objective!r} must be one of {', '.join(OBJECTIVES)} "
                         "or a callable of the steady_objectives dict")
    if objective == "pmax":
        if band is None:
            raise SweepError("objective 'pmax' needs band=(f_lo, f_hi) in Hz")
        check_band(band)
    elif freq is None or not (math.isfinite(float(freq)) and float(freq) > 0):
        raise SweepError(f"objective {objective!r} needs freq > 0 in Hz (allowed range "
                         f"(0, inf)), got {freq!r}")
    check_int("starts", starts, 1)
    if isinstance(max_field, bool) or not (math.isfinite(float(max_field))
                                           and float(max_field) > 0):
        raise SweepError(f"max_field = {max_field!r} must be > 0 V/m (allowed range (0, inf))")
    for k, v in (x0 or {}).items():
        if k not in bounds:
            raise SweepError(f"x0 names {k!r}, which is not in vary")
        lo, hi = bounds[k]
        if not (math.isfinite(float(v)) and lo <= float(v) <= hi):
            raise SweepError(f"x0[{k!r}] = {v!r} is outside its bounds [{lo:g}, {hi:g}]")
    return bounds


def optimise(model: Model, vary: dict, objective: str | Callable = "pmax", *, mass=None,
             damping=None, payload=None, band=None, freq=None, drive: str = "A", phase=None,
             max_field: float = 80e6, starts: int = 8, seed: int = 0, x0: dict | None = None,
             maxiter: int = 20, gtol: float = 1e-3, settings: Steady = DESIGN_STEADY,
             grid: int = 8, refine: int = 6, devices: tuple | None = None,
             progress: bool = True) -> OptimiseResult:
    """Maximise steady-state power (or efficiency, or any objective) over bounded parameters.

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model` (the start design).
    - `vary`: ``{name: (lower, upper)}``: model parameter paths (:mod:`jaxdea.params`) or
      ``"mass"``, ``"damping"`` (or a payload law's ``"payload.<name>"``), with their
      bounds.
    - `objective`: ``"pmax"`` (P_max over ``band``), ``"power"`` (P_out at ``freq``),
      ``"efficiency"`` (at ``freq``), or a callable of the :func:`steady_objectives` dict
      at ``freq`` returning a scalar (JAX operations) to maximise.
    - `mass`, `damping`: payload M (kg) and c (N s/m).
    - `payload`: a payload law (:class:`jaxdea.Drag`, ... or a sum) instead of `damping`.
    - `band`: ``(f_lo, f_hi)`` Hz for ``"pmax"``; `freq`: Hz for the others.
    - `drive`, `phase`: the drive case.
    - `max_field`: largest nominal field at the static equilibrium, V/m.
    - `starts`: number of starts (the first is ``x0`` or the model's values if inside the
      bounds, the others a Latin hypercube from ``seed``; a start above ``max_field`` is
      moved towards the first start, to the field limit, if the first start is within it).
    - `maxiter`: most iterations; `gtol`: stop when the projected gradient in the unit box
      is below ``gtol * |objective|``.
    - `settings`, `grid`, `refine`: the periodic solve and the peak search.
    - `devices`: the JAX devices the starts are split over (each runs its share to the end;
      default: every local device, e.g. one per core after :func:`jaxdea.use_cpu_cores`).
    - `progress`: a progress bar over the evaluations (the screening of the starts, each
      iteration, the final solve from rest), with the best objective so far.

    Each iteration continues every start's orbits from its last accepted design (the
    settling stage then starts next to the new orbit); the returned design's objective is
    re-solved from rest, so it is the steady state that the actuator reaches from rest.

    **Returns:**

    An :class:`OptimiseResult` (the best feasible design found).
    """
    bounds = _check_inputs(model, vary, objective, band, freq, starts, max_field, x0, payload)
    keys, full, pay = split_names(resolve(model, list(vary), payload))
    lo = np.array([bounds[k][0] for k in keys])
    hi = np.array([bounds[k][1] for k in keys])
    n = len(keys)
    rng = np.random.default_rng(seed)
    u = (rng.permuted(np.tile(np.arange(starts), (n, 1)), axis=1).T
         + rng.random((starts, n))) / starts
    model_vals = [_current(model, k, mass, damping, payload) for k in keys]
    first = np.array([(x0 or {}).get(k, v) for k, v in zip(keys, model_vals)], float)
    if np.all((lo <= first) & (first <= hi)):
        u[0] = (first - lo) / (hi - lo)
    kw = dict(mass=mass, damping=damping, drive=drive, phase=phase, payload=payload)
    if objective == "pmax":
        lo_f, hi_f = check_band(band)
        build = make_builder(model, full, pay, freq=np.linspace(lo_f, hi_f, grid), shift=True,
                         **kw)
    else:
        build = make_builder(model, full, pay, freq=np.array([float(freq)]), shift=False, **kw)

    def fields(x):
        return np.array([float(nominal_field(_design(model, keys, full, lo + xi * (hi - lo))))
                         for xi in x])

    devices = tuple(jax.devices() if devices is None else devices)

    def evaluate(x, initial=None):
        """Objective, gradient (unit box), peak f, failure flags, the orbits (start states
        for a continuation; None for a callable objective) and metrics of the designs
        ``x``."""
        theta = lo + x * (hi - lo)
        if objective == "pmax":
            r = peak_designs(build, np.concatenate([theta, np.zeros((len(x), 1))], 1),
                             (lo_f, hi_f), grid=grid, refine=refine, settings=settings,
                             initial=initial, devices=devices)
            val, g, fpk, st = r["P_max"], r["grad"][:, :-1], r["f"], r["status"]
            orbits, met = r["coarse"], r["metrics"]
        elif callable(objective):
            val, g = [], []
            for th in theta:
                v, gr = jax.value_and_grad(lambda t: objective(_metrics(build, t, settings)))(
                    jnp.asarray(th))
                val.append(float(v))
                g.append(np.asarray(gr))
            val, g, fpk = np.array(val), np.array(g), None
            st = np.where(np.isfinite(val), 0, 4)
            orbits, met = None, None
        else:
            r = solve_designs(build, theta, settings=settings, jac=True, initial=initial,
                              devices=devices)
            i = 0 if objective == "power" else 2
            val, g, fpk, st = r.values[:, 0, i], r.jac[:, 0, i, :], None, r.status[:, 0]
            orbits, met = r.converged_states(), r.values[:, 0]
        bad = (st != 0) | ~np.isfinite(val)
        return np.where(bad, -np.inf, val), np.nan_to_num(g) * (hi - lo), fpk, bad, orbits, met

    x = _pull_inside(np.clip(u, 0.0, 1.0), fields, max_field)
    e = fields(x)
    from tqdm.auto import tqdm

    with tqdm(total=int(maxiter) + 2, desc="optimise", unit="evaluation",
              disable=not progress) as bar:
        x, val, g, fpk, met, history, path, stopped, start_val = _search(
            evaluate, fields, x, e, lo, hi, max_field, maxiter, gtol, bar)
    e = fields(x)
    ok = (e <= max_field) & np.isfinite(val)
    if not ok.any():
        raise JaxdeaError("no start gave a feasible design (orbit status 0 and nominal field "
                          f"<= max_field = {max_field:g} V/m): widen the bounds or add starts")
    k = int(np.argmax(np.where(ok, val, -np.inf)))
    theta = lo + x[k] * (hi - lo)
    best = _design(model, keys, full, theta)
    active = [f"{name} at its {'lower' if x[k][i] <= 0 else 'upper'} bound "
              f"{(lo if x[k][i] <= 0 else hi)[i]:g}"
              for i, name in enumerate(keys) if x[k][i] <= 0 or x[k][i] >= 1]
    if e[k] >= max_field * (1 - 1e-3):
        active.append(f"nominal field at max_field ({e[k] / 1e6:.4g} MV/m)")
    metrics = {} if met is None else dict(zip(("P_out", "P_in", "efficiency", "amplitude"),
                                              map(float, met[k])))
    return OptimiseResult(
        model=best, values=dict(zip(keys, map(float, theta))), objective=float(val[k]),
        f_at_P_max=None if fpk is None else float(fpk[k]),
        gradient=dict(zip(keys, map(float, g[k] / (hi - lo)))), active=active,
        field=float(e[k]), start_objective=start_val, history=history, path=path,
        metrics=metrics, stopped=str(stopped[k]))


def _search(evaluate, fields, x, e, lo, hi, max_field, maxiter, gtol, bar):
    """:func:`optimise`'s multi-start projected gradient ascent in the unit box, from the
    starts ``x`` (nominal fields ``e``): the screening, at most ``maxiter`` iterations (a
    Barzilai-Borwein step per start, halved until the design is within ``max_field``, kept
    if the objective did not fall), then every start solved from rest again. ``bar``
    advances once per evaluation.

    **Returns:**

    ``(x, val, g, fpk, met, history, path, stopped, start_val)``: the designs, their
    objectives, unit-box gradients, peak frequencies and metrics, the objectives and
    designs per iteration, why each start stopped, and the first start's objective.
    """
    # screening: every start in one batched call; `here`: the orbits of the designs x
    # (continuation's start)
    val, g, fpk, bad, here, met = evaluate(x)
    start_val = float(val[0])
    feasible = (e <= max_field) & ~bad
    val = np.where(feasible, val, -np.inf)  # infeasible starts are dropped
    _advance(bar, val)
    history = [val.copy()]
    path = [lo + x * (hi - lo)]
    alpha = 0.1 / np.maximum(np.max(np.abs(g), axis=1), 1e-300)
    done = ~feasible  # infeasible starts are dropped
    stopped = np.where(feasible, "maxiter", "infeasible").astype(object)
    for _ in range(int(maxiter)):
        pg = _projected(x, g)
        small = ~done & (np.max(np.abs(pg), axis=1) <= gtol * np.abs(val))
        stopped[small] = "gradient"
        done |= small
        if done.all():
            break
        prop = x.copy()
        for k in np.nonzero(~done)[0]:
            a = alpha[k]
            for _h in range(40):
                prop[k] = np.clip(x[k] + a * g[k], 0.0, 1.0)
                if fields(prop[k:k + 1])[0] <= max_field:
                    break
                a = 0.5 * a
            alpha[k] = a
        v2, g2, f2, b2, there, met = evaluate(prop, here)
        better = ~done & ~b2 & (v2 >= val)
        if here is not None:
            here = jax.tree_util.tree_map(lambda a, b: np.where(
                better.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), there, here)
        s, yv = prop - x, -(g2 - g)
        sy = np.sum(s * yv, axis=1)
        bb = np.where(sy > 0, np.sum(s * s, axis=1) / np.where(sy > 0, sy, 1.0), 2 * alpha)
        alpha = np.where(better, np.clip(bb, 1e-3 * alpha, 1e3 * alpha),
                         np.where(done, alpha, 0.25 * alpha))
        x = np.where(better[:, None], prop, x)
        val, g = np.where(better, v2, val), np.where(better[:, None], g2, g)
        fpk = None if fpk is None else np.where(better, f2, fpk)
        short = ~done & (alpha * np.max(np.abs(g), axis=1) < 1e-7)
        stopped[short] = "step"
        done |= short
        history.append(val.copy())
        path.append(lo + x * (hi - lo))
        _advance(bar, val)
    bar.total = bar.n + (len(history) > 1)  # every start may stop before maxiter
    if len(history) > 1:  # the orbits were continued: report the steady states from rest
        val, g, fpk, _, _, met = evaluate(x)
        _advance(bar, val)
    return x, val, g, fpk, met, history, path, stopped, start_val


def _advance(bar, val):
    """One evaluation done: the bar moves on and shows the best objective so far."""
    best = np.max(val) if np.size(val) else -np.inf
    bar.set_postfix_str(f"best objective {best:.6g}" if np.isfinite(best)
                        else "no feasible start yet", refresh=False)
    bar.update(1)


def _pull_inside(x, fields, max_field):
    """Starts above the field limit moved towards the first start (if that one is within
    it) to the last point within it on the line between them (bisection), so that no
    Latin-hypercube start is lost to the field limit; the others are left as they are."""
    e = fields(x)
    if e[0] > max_field or (e <= max_field).all():
        return x
    x = x.copy()
    for k in np.nonzero(e > max_field)[0]:
        a, b = 0.0, 1.0  # fractions of the way from x[0] to x[k]: a within, b above
        for _ in range(30):
            t = 0.5 * (a + b)
            if fields((x[0] + t * (x[k] - x[0]))[None])[0] <= max_field:
                a = t
            else:
                b = t
        x[k] = x[0] + a * (x[k] - x[0])
    return x


def _projected(x, g):
    """The projected gradient (ascent) in the unit box."""
    return np.where(((x <= 0) & (g < 0)) | ((x >= 1) & (g > 0)), 0.0, g)


def _current(model, key, mass, damping, payload=None):
    if key == "mass" and mass is None and payload is not None:
        return float(np.asarray(payload.mass))
    if key in ("mass", "damping"):
        return {"mass": mass, "damping": damping}[key] or 0.0
    if key.startswith(LAW):
        return law_value(payload, key)
    return float(list(get_params(model, [key]).values())[0])


def _design(model, keys, full, theta):
    """The model with the model parameters among ``keys`` set to ``theta``."""
    return set_params(model, {k: float(t) for k, t in zip(keys, theta) if k not in
                              ("mass", "damping") and not k.startswith(LAW)})


def _metrics(build, theta, settings):
    from ..engine.sensitivity import steady_metrics
    out = steady_metrics(build, theta, settings)
    return {k: v[0] for k, v in out.items()}
