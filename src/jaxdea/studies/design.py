"""Design objectives at the periodic steady state, differentiable in named parameters.

:func:`steady_objectives` gives P_out, P_in, efficiency and amplitude of the converged
periodic orbit at given frequencies; :func:`peak_power` gives P_max over a band and the
frequency where it occurs. Both are differentiable (``jax.grad``, ``jax.jacfwd``,
``jax.jacrev``) in a dict of named scalars: model parameters by their
:mod:`jaxdea.params` path (``"actuator.spring_stiffness"``, ``"membrane.prestretch"``,
``"voltage"``, ``"duty"``, ...) and the payload and drive values ``"mass"``, ``"damping"``,
``"freq"``. The derivatives are implicit at the orbit (:mod:`jaxdea.engine.sensitivity`);
P_max uses the envelope theorem: ``dP_max/dtheta = dP/dtheta`` at the peak frequency f*.

The peak is found by batched periodic sweeps (:func:`peak_designs`): ``grid`` evenly
spaced frequencies, each with ``dP/df`` from the same implicit derivative, then levels of
``grid`` cells placed from every sample so far: first inside every interval where ``dP/df``
turns from + to - (a resonance narrower than the grid spacing is bracketed by its slopes
even where P at both samples is low), narrowing the best brackets until the best is narrow
against its peak's width, then a final level over it with the full gradient, where P_max,
its gradient and the metrics are fitted at the root of ``dP/df`` (the envelope theorem
holds at that root, not at a cell next to it). Each cell is warm-started from the orbit of
its nearest sample.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import SweepError, finite_array
from ..engine.implicit import implicit
from ..engine.sensitivity import METRICS, Steady, solve_designs, stack_designs
from ..engine.step_control import StepControl
from ..models.cone import Model
from .builder import Builder, check_values, make_builder, resolve, split_names, theta_of
from .loadings import check_cone_model
from .peak_search import bracket_ready, next_frequencies, stationary_point

#: Default periodic solve of the design study: Newton to 1e-8, engine rtol 1e-7 (central
#: differences of P_out agree with the implicit derivative to ~1e-7 there).
DESIGN_STEADY = Steady(tol=1e-8, warmup=30, newton=10,
                       control=StepControl(rtol=1e-7, dt_max=1e-3))


class _AtFrequency(eqx.Module):
    build: Builder
    settings: Steady = eqx.field(static=True)

    def __call__(self, theta, need_jac):
        r = solve_designs(self.build, theta[None], settings=self.settings, jac=need_jac)
        values = {k: r.values[0, :, i] for i, k in enumerate(METRICS)}
        values["status"] = r.status[0].astype(float)
        jacs = None if r.jac is None else {k: r.jac[0, :, i] for i, k in enumerate(METRICS)}
        return values, jacs


def steady_objectives(model: Model, values: dict | None = None, *, mass=None, damping=None,
                      payload=None,
                      freq=None, drive: str = "A", phase: float | None = None,
                      settings: Steady = DESIGN_STEADY) -> dict[str, jax.Array]:
    """Metrics of the periodic steady state, differentiable in named parameters.

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model`.
    - `values`: ``{name: scalar}``: model parameters (paths of :mod:`jaxdea.params`) and
      ``"mass"`` (kg), ``"damping"`` (N s/m), ``"freq"`` (Hz) set to these values and
      differentiated; e.g. ``jax.grad(lambda v: steady_objectives(model, v, ...)["P_out"])``.
    - `mass`, `damping`: payload M (kg) and c (N s/m), unless in ``values``.
    - `payload`: a payload law (:class:`jaxdea.Drag`, ... or a sum) instead of `damping`;
      its parameters are named ``"payload.<name>"`` (e.g. ``"payload.quadratic"``).
    - `freq`: drive frequency or 1-D array of them (Hz), unless ``"freq"`` is in ``values``.
    - `drive`, `phase`: the drive case (``"A"``, ``"B"``, ``"both"`` with B's delay, rad).
    - `settings`: the periodic solve (:class:`~jaxdea.engine.sensitivity.Steady`).

    **Returns:**

    ``{"P_out" (W), "P_in" (W), "efficiency", "amplitude" (m), "status"}``, each with the
    shape of ``freq`` (NaN where status != 0).
    """
    values = dict(values or {})
    mapping = resolve(model, list(values), payload)
    check_values(model, mapping, values)
    keys, full, pay = split_names(mapping)
    if "freq" in pay:
        if freq is not None:
            raise SweepError("freq is given twice: in values and as freq=; drop one")
        freq = 1.0
    if freq is None:
        raise SweepError("freq is needed (allowed range (0, inf) Hz), got None")
    shape = np.shape(freq)
    f = finite_array("freq", freq, positive=True)
    build = make_builder(model, full, pay, mass=mass, damping=damping, payload=payload, freq=f,
                         drive=drive, phase=phase, shift=False)
    out = implicit(_AtFrequency(build, settings), theta_of(values, keys))
    return {k: v.reshape(shape) for k, v in out.items()}


def peak_designs(build: Builder, theta, band, *, grid: int = 8, refine: int = 6,
                 settings: Steady = DESIGN_STEADY, jac: bool = True, initial=None,
                 devices: tuple | None = None) -> dict[str, np.ndarray]:
    """P_max over a band for a batch of designs (host-side; the study's workhorse).

    Level 0 solves ``grid`` evenly spaced frequencies; each later level solves ``grid``
    more, placed by :func:`next_frequencies` from every sample so far (P and the implicit
    dP/df): bracketing levels put cells inside the intervals where dP/df turns from + to -
    (every such hill at the first level, so that a resonance narrower than the grid
    spacing is bracketed by its slopes, not lost between samples), until the best bracket
    is narrow against the peak's width (:func:`bracket_ready`; at least one bracketing
    level); the final level (with the full gradient) spans that bracket, and
    :func:`stationary_point` gives P_max, its gradient and metrics where dP/df = 0. Each
    cell starts from the orbit of its nearest sample.

    **Arguments:**

    - `build`: a :class:`Builder` with ``grid`` cells and a frequency shift (last entry of
      ``theta``, held at 0 here).
    - `theta`: ``(K, n)`` designs (the shift included).
    - `band`: ``(f_lo, f_hi)``, Hz.
    - `grid`: cells per level; `refine`: most levels after the first (the final level
      included; 0: the best cell of the first level). Where the levels run out before the
      bracket is narrow (:func:`bracket_ready`), P_max is the best cell of the final level,
      not the fitted root.
    - `settings`: the periodic solve; `jac`: also the gradient (envelope theorem).
    - `initial`: start states ``(K, grid, ...)`` of the first level's cells (e.g. the
      ``"coarse"`` orbits of a nearby design: a continuation); default, and for cells whose
      start state is NaN: rest.
    - `devices`: split the designs over these JAX devices (:func:`solve_designs`).

    **Returns:**

    ``{"P_max": (K,), "f": (K,), "status": (K,), "grad": (K, n) or None, "metrics": (K, 4)
    (:data:`~jaxdea.engine.sensitivity.METRICS` at the peak), "coarse": the orbits' start
    states on the first level (K, grid, ...), NaN where not converged, "levels": the number
    of levels solved}``.
    """
    theta = np.asarray(theta, float)
    k, n = theta.shape
    f = np.tile(np.linspace(band[0], band[1], grid), (k, 1))
    shift = (n - 1,)  # the bracketing levels' only derivative: dP/df
    state, coarse, final, level = initial, None, refine == 0, 0
    ready = np.zeros(k, bool)  # the final level spans a bracket narrow enough for fits
    seen_f, seen_p, seen_g, seen_y = [], [], [], []  # every level's samples
    while True:
        r = _solve_grid(build, theta, f, state, settings, jac and final, shift, devices)
        if level == 0:
            coarse = r.converged_states()
        p = np.where(r.status == 0, r.values[..., 0], -np.inf)
        g = r.jac[..., 0, -1]
        if final:
            break
        for seen, new in zip((seen_f, seen_p, seen_g, seen_y), (f, p, g, r.converged_states())):
            seen.append(new)
        fa, pa, ga = (np.concatenate(s, axis=1) for s in (seen_f, seen_p, seen_g))
        level += 1
        ready = np.array([bracket_ready(fa[i], pa[i], ga[i], band) for i in range(k)])
        final = level >= refine or (level > 1 and ready.all())
        f = np.stack([next_frequencies(fa[i], pa[i], ga[i], level, grid, band, final)
                      for i in range(k)])
        near = np.abs(fa[:, :, None] - f[:, None, :]).argmin(axis=1)  # (K, grid)
        ya = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *seen_y)
        state = jax.tree_util.tree_map(
            lambda a: np.take_along_axis(a, near.reshape(near.shape + (1,) * (a.ndim - 2)),
                                         axis=1), ya)
    nm = r.values.shape[-1]
    fstar, pmax, status = np.zeros(k), np.full(k, np.nan), np.max(r.status, axis=1)
    metrics, grad = np.full((k, nm), np.nan), (np.full((k, n), np.nan) if jac else None)
    for i in range(k):
        if not np.isfinite(p[i]).any():
            fstar[i] = f[i, 0]
            continue
        rows = r.values[i] if not jac else np.concatenate([r.values[i], r.jac[i, :, 0, :]], 1)
        if ready[i]:
            fstar[i], at = stationary_point(f[i], p[i], g[i], rows)
        else:  # levels ran out before the bracket was narrow: the best cell
            fstar[i], at = f[i, np.argmax(p[i])], rows[np.argmax(p[i])]
        pmax[i], metrics[i], status[i] = at[0], at[:nm], 0
        if jac:
            grad[i] = at[nm:]
    return dict(P_max=pmax, f=fstar, status=status, grad=grad, coarse=coarse,
                metrics=metrics, levels=level + 1)


def _solve_grid(build, theta, f, state, settings, full_jac, shift, devices=None):
    """One level: the designs' cells at frequencies ``f`` (K, G), in one batched call, with
    the Jacobian over the shift (and every parameter if ``full_jac``)."""
    k = theta.shape[0]
    builds = [eqx.tree_at(lambda x: x.freq, build, jnp.asarray(f[i])) for i in range(k)]
    # host arrays as they are: under jax.grad of peak_power, jnp.asarray here would give
    # tracers, which the host-side solve cannot read
    init = None if state is None else jax.tree_util.tree_map(np.asarray, state)
    return solve_designs(stack_designs(builds), theta, settings=settings, initial=init,
                         jac=True if full_jac else shift, stacked=True, devices=devices)


class _Peak(eqx.Module):
    build: Builder
    band: tuple = eqx.field(static=True)
    grid: int = eqx.field(static=True)
    refine: int = eqx.field(static=True)
    settings: Steady = eqx.field(static=True)

    def __call__(self, theta, need_jac):
        th = np.concatenate([theta, [0.0]])[None]
        r = peak_designs(self.build, th, self.band, grid=self.grid, refine=self.refine,
                         settings=self.settings, jac=need_jac)
        values = {"P_max": r["P_max"][0], "f_at_P_max": r["f"][0],
                  "status": float(r["status"][0])}
        jacs = None if not need_jac else {"P_max": r["grad"][0, :-1]}
        return values, jacs


def check_band(band) -> tuple[float, float]:
    """``band`` as ``(f_lo, f_hi)`` with ``0 < f_lo < f_hi`` finite; else SweepError."""
    try:
        lo, hi = (float(x) for x in band)
    except (TypeError, ValueError):
        raise SweepError(f"band must be a pair (f_lo, f_hi) in Hz, got {band!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        raise SweepError(f"band = ({lo:g}, {hi:g}) Hz: need 0 < f_lo < f_hi, finite (allowed "
                         "range (0, inf) Hz)")
    return lo, hi


def peak_power(model: Model, values: dict | None = None, *, mass=None, damping=None,
               payload=None,
               band=(1.0, 200.0), drive: str = "A", phase: float | None = None,
               grid: int = 8, refine: int = 6,
               settings: Steady = DESIGN_STEADY) -> dict[str, jax.Array]:
    """P_max over a frequency band at the periodic steady state, differentiable in named
    parameters (envelope theorem: ``dP_max/dtheta = dP/dtheta`` at f*).

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model`.
    - `values`: ``{name: scalar}`` as in :func:`steady_objectives` (not ``"freq"``).
    - `mass`, `damping`: payload M (kg) and c (N s/m), unless in ``values``.
    - `payload`: a payload law (:class:`jaxdea.Drag`, ... or a sum) instead of `damping`;
      its parameters are named ``"payload.<name>"`` (e.g. ``"payload.quadratic"``).
    - `band`: ``(f_lo, f_hi)``, Hz.
    - `drive`, `phase`: the drive case.
    - `grid`: frequencies per level (>= 3); `refine`: most levels after the first
      (>= 0; :func:`peak_designs`).
    - `settings`: the periodic solve.

    **Returns:**

    ``{"P_max" (W), "f_at_P_max" (Hz; zero derivative), "status"}``.
    """
    values = dict(values or {})
    mapping = resolve(model, list(values), payload)
    check_values(model, mapping, values)
    keys, full, pay = split_names(mapping)
    if "freq" in pay:
        raise SweepError("freq cannot be varied in peak_power: the band fixes it")
    lo, hi = check_band(band)
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 3:
        raise SweepError(f"grid must be an integer >= 3, got {grid!r}")
    if isinstance(refine, bool) or not isinstance(refine, int) or refine < 0:
        raise SweepError(f"refine must be an integer >= 0, got {refine!r}")
    build = make_builder(model, full, pay, mass=mass, damping=damping, payload=payload,
                     freq=np.linspace(lo, hi, grid), drive=drive, phase=phase, shift=True)
    return implicit(_Peak(build, (lo, hi), grid, refine, settings), theta_of(values, keys))


def objective_function(model: Model, names, objective: str | Callable, **kw) -> Callable:
    """``values -> scalar`` for :func:`jaxdea.optimise`'s objectives (``"pmax"``,
    ``"power"``, ``"efficiency"`` or a callable of the :func:`steady_objectives` dict).

    **Arguments:**

    - `model`, `names`: the model and the varied names.
    - `objective`: the objective.
    - `kw`: ``mass``, ``damping`` or ``payload``, ``freq`` or ``band``, ``drive``, ``phase``,
      ``settings``.

    **Returns:**

    The function of a ``{name: value}`` dict, differentiable by ``jax.grad``.
    """
    kw = dict(kw)
    band = kw.pop("band", None)
    if objective == "pmax":
        kw.pop("freq", None)
        return lambda v: peak_power(model, v, band=band, **kw)["P_max"]
    kw.pop("grid", None)
    kw.pop("refine", None)
    key = {"power": "P_out", "efficiency": "efficiency"}.get(objective)
    if key is not None:
        return lambda v: jnp.sum(steady_objectives(model, v, **kw)[key])
    return lambda v: objective(steady_objectives(model, v, **kw))


def design_map(model: Model, values: dict, *, mass=None, damping=None, payload=None,
               band=(1.0, 200.0),
               drive: str = "A", phase: float | None = None, grid: int = 8, refine: int = 6,
               settings: Steady = DESIGN_STEADY, devices: tuple | None = None,
               progress: bool = True):
    """P_max over a band for every design of a grid of parameter values, in batched calls.

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model`.
    - `values`: ``{name: 1-D array}``: model parameter paths (:mod:`jaxdea.params`) or
      ``"mass"``, ``"damping"``; the designs are their outer product (one map axis each).
    - `mass`, `damping`: payload M (kg) and c (N s/m), unless in ``values``.
    - `payload`: a payload law (:class:`jaxdea.Drag`, ... or a sum) instead of `damping`;
      its parameters are named ``"payload.<name>"`` (e.g. ``"payload.quadratic"``).
    - `band`: ``(f_lo, f_hi)``, Hz; `grid`, `refine`: the peak search (:func:`peak_power`).
    - `drive`, `phase`: the drive case.
    - `settings`: the periodic solve.
    - `devices`: split the designs over these JAX devices (default: every local device).
    - `progress`: a progress bar over the batches.

    **Returns:**

    An ``xarray.Dataset`` with one dimension per name: ``P_max`` (W), ``f_at_P_max`` (Hz),
    ``efficiency``, ``P_in`` (W) and ``amplitude`` (m) at the peak, ``field`` (nominal
    field at the static equilibrium, V/m) and ``status`` (0 = a stable periodic orbit at
    every frequency searched near the peak).
    """
    import xarray as xr
    from tqdm.auto import tqdm

    from ..params import set_params
    from .loadings import nominal_field

    check_cone_model(model)
    if not isinstance(values, dict) or not values:
        raise SweepError("values must be a non-empty dict {name: 1-D array}")
    arrays = {k: finite_array(k, v) for k, v in values.items()}
    for k, a in arrays.items():
        if a.ndim != 1 or a.size < 1:
            raise SweepError(f"values[{k!r}] must be a 1-D array of at least one value")
    mapping = resolve(model, list(arrays), payload)
    check_values(model, mapping, arrays)
    if "freq" in mapping.values():
        raise SweepError("freq cannot be a design axis: the band fixes it")
    lo, hi = check_band(band)
    keys, full, pay = split_names(mapping)
    names = list(arrays)
    mesh = np.meshgrid(*arrays.values(), indexing="ij")
    shape = mesh[0].shape
    theta = np.stack([mesh[names.index(k)].ravel() for k in keys], axis=1)
    build = make_builder(model, full, pay, mass=mass, damping=damping, payload=payload,
                         freq=np.linspace(lo, hi, grid), drive=drive, phase=phase, shift=True)
    devices = tuple(jax.devices() if devices is None else devices)
    batch = 8 * len(devices)
    out = {k: np.full(theta.shape[0], np.nan) for k in ("P_max", "f", "status", "field",
                                                        *METRICS)}
    with tqdm(total=theta.shape[0], desc="design map", unit="design",
              disable=not progress) as bar:
        for a in range(0, theta.shape[0], batch):
            th = theta[a:a + batch]
            padded = np.concatenate([th, np.repeat(th[-1:], batch - len(th), 0)])  # one shape
            r = peak_designs(build, np.concatenate([padded, np.zeros((batch, 1))], 1),
                             (lo, hi), grid=grid, refine=refine, settings=settings, jac=False,
                             devices=devices)
            r = {k: v[:len(th)] for k, v in r.items() if k not in ("coarse", "levels", "grad")}
            sl = slice(a, a + len(th))
            out["P_max"][sl], out["f"][sl], out["status"][sl] = r["P_max"], r["f"], r["status"]
            for i, m in enumerate(METRICS):
                out[m][sl] = r["metrics"][:, i]
            n_model = len(full)
            if n_model:
                out["field"][sl] = [float(nominal_field(set_params(model, dict(zip(
                    keys[:n_model], map(float, t[:n_model])))))) for t in th]
            else:  # only payload axes vary: the model's own field for every design
                out["field"][sl] = float(nominal_field(model))
            bar.update(len(th))
    dims = tuple(names)
    var = lambda k: (dims, out[k].reshape(shape))  # noqa: E731
    return xr.Dataset(
        {"P_max": var("P_max"), "f_at_P_max": var("f"), "efficiency": var("efficiency"),
         "P_in": var("P_in"), "amplitude": var("amplitude"), "field": var("field"),
         "status": (dims, out["status"].reshape(shape).astype(int))},
        coords={k: a for k, a in arrays.items()},
        attrs={"band_Hz": [lo, hi], "drive": drive, "model": model.actuator.name,
               "P_max": "largest steady P_out over the band (W); efficiency, P_in and "
                        "amplitude at that frequency"})
