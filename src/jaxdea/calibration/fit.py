"""Parameter identification: fit any subset of a model's parameters to measured data.

``calibrate(model, data, fit=[...], bounds={...}, method=...)`` returns a
:class:`CalibrationResult` with the fitted model, the loss history, the papers' error metrics
``e_rms`` / ``e_m`` (paper 001 Sec 4.2, paper 002 eq 26) and a Gauss-Newton curvature /
covariance estimate at the optimum.

Parameters
----------
A parameter is named by its path in the model pytree (``"actuator.membrane.dielectric.mu_A"``)
or by any dot-suffix of that path that is unique (``"dielectric.mu_A"``, ``"tau"`` when only
one ``tau`` exists); :func:`~jaxdea.params.parameter_names` lists them. Unfitted
parameters are held.

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
``method`` is an optimiser of :mod:`jaxdea.calibration.optimisers` (:class:`LBFGS`,
:class:`Adam`, :class:`LM`, :class:`DE`, each carrying its settings) or its name
(``"lbfgs"``, ``"adam"``, ``"lm"``, ``"de"``, with the settings from ``calibrate``'s keywords):

- ``"lbfgs"``: scipy's L-BFGS-B on ``z`` with the exact JAX gradient.
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
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError, DataError
from ..params import make_params, with_theta
from .data import Data, FrequencyResponse, TimeSeries
from .objective import LOSSES, Objective
from .optimisers import METHODS, OPTIMISERS, AbstractOptimiser, optimiser_for
from .predictors import default_predict

__all__ = ["CalibrationResult", "calibrate", "error_metrics"]


def error_metrics(measured, predicted) -> tuple[float, float]:
    """Paper 002 eq 26 / paper 001 Sec 4.2: ``(e_rms, e_m)`` in percent.

    ``e_m = max|z_e - z_m| / (max z_m - min z_m) * 100 %`` as printed. ``e_rms`` is printed as
    ``sqrt(mean (z_e - z_m)^2) * 100 %`` with no normaliser, which only makes sense as a
    percentage of a reference; we divide it by the same model range as ``e_m``, so both are
    dimensionless percentages of the model's peak-to-peak output.

    **Arguments:**

    - `measured`: the data ``z_e`` (any shape; flattened).
    - `predicted`: the model output ``z_m`` at the same points.

    **Returns:**

    ``(e_rms, e_m)`` in percent of the model's range (of its largest magnitude if flat).
    """
    ze = np.asarray(measured, dtype=float).ravel()
    zm = np.asarray(predicted, dtype=float).ravel()
    span = float(np.max(zm) - np.min(zm))
    if not span > 0:
        span = float(np.max(np.abs(zm))) or 1.0
    err = ze - zm
    return (float(np.sqrt(np.mean(err * err)) / span * 100.0),
            float(np.max(np.abs(err)) / span * 100.0))


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
    method: str  #: the optimiser's name: "lbfgs", "adam", "lm" or "de"
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
    #: the fitted payload law (fits with ``payload=``), else None
    payload: Any = None
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


def _curvature(obj: Objective, z, params, theta, loss, flat_threshold, jac):
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


def calibrate(model, data: Data, fit, *, bounds=None,
              method: str | AbstractOptimiser = "lbfgs", loss: str = "mse", seed: int = 0,
              predict: Callable | None = None, transforms=None, jac: str = "auto",
              maxiter: int | None = None, learning_rate: float = 0.05, tol: float = 1e-10,
              de_options=None, curvature: bool = True, flat_threshold: float = 0.5,
              verbose: bool = False, payload=None, progress: bool = True) -> CalibrationResult:
    """Fit the parameters ``fit`` of ``model`` to ``data``.

    **Arguments:**

    - `model`: the model; its values are the start values and the unfitted ones are held.
    - `data`: a :class:`~jaxdea.calibration.TimeSeries` or
      :class:`~jaxdea.calibration.FrequencyResponse`.
    - `fit`: the names of the parameters to fit (paths or unique suffixes, see
      :func:`~jaxdea.calibration.resolve_names`).
    - `bounds`: ``{name: (lower, upper)}`` in the parameter's units (needed by ``"de"``).
    - `method`: an optimiser (:class:`~jaxdea.calibration.LBFGS`, ``Adam``, ``LM``, ``DE``,
      carrying its settings) or its name ``"lbfgs"`` | ``"adam"`` | ``"lm"`` | ``"de"``, whose
      settings then come from ``maxiter``, ``learning_rate``, ``tol`` and ``de_options``.
    - `loss`: ``"mse"`` | ``"relative"`` | ``"log"`` (see the module doc).
    - `seed`: random seed (``"de"``).
    - `predict`: ``predict(model, data) -> {channel: array}``; default from
      :func:`~jaxdea.calibration.predictors.default_predict`.
    - `transforms`: ``{name: "log" | "linear"}``.
    - `jac`: ``"auto"`` (forward mode for frequency responses, reverse mode for time series),
      ``"fwd"`` or ``"rev"``.
    - `maxiter`: iterations (generations for DE; default 200 / 2000 / 100 / 115 for lbfgs /
      adam / lm / de). Only with a method name.
    - `learning_rate`: Adam's step in z (with a method name).
    - `tol`: the tolerance of lbfgs, adam and lm (with a method name).
    - `de_options`: overrides of :data:`~jaxdea.calibration.DE_PAPER` and of scipy's
      ``tol``/``atol``/``init``. Only with a method name.
    - `curvature`: compute the Gauss-Newton curvature and covariance at the optimum.
    - `flat_threshold`: a relative 1-sigma above which a parameter is reported as not
      identified (``result.flat``).
    - `verbose`: print progress.
    - `progress`: a progress bar over the optimiser's iterations (generations for DE), with
      the loss.
    - `payload`: the payload law the data were measured with (:class:`jaxdea.Drag`, ... or
      a sum; cone models and frequency responses only): the data's ``mass`` column is its
      mass and its ``damping`` column is not used. Its parameters can be fitted as
      ``"payload.<name>"`` (e.g. ``"payload.quadratic"``); the fitted law is
      ``result.payload``.

    **Returns:**

    A :class:`CalibrationResult`. Raises :class:`~jaxdea.CalibrationError` on bad arguments
    or a diverged fit, :class:`~jaxdea.DataError` on unusable data.
    """
    if isinstance(method, AbstractOptimiser):
        name = method.name
        given = [k for k, v in (("maxiter", maxiter), ("de_options", de_options))
                 if v not in (None, {})]
        if given:
            raise CalibrationError(f"{' and '.join(given)} only with a method name: the "
                                   f"optimiser {method!r} carries its own settings")
        searches_box = method.searches_box
    elif isinstance(method, str) and method in METHODS:
        name = method
        searches_box = OPTIMISERS[method].searches_box
    else:
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
    if payload is not None:
        model = _loaded(model, data, payload)
    params = make_params(model, fit, bounds, transforms)
    if searches_box:
        open_ = [p.name for p in params if not (math.isfinite(p.ulo) and math.isfinite(p.uhi))]
        if open_:
            raise CalibrationError(f"method {name!r} searches a box: give finite bounds for "
                                   f"{', '.join(open_)}")
    predict = predict or default_predict(model, data)
    obj = Objective(model, data, params, predict, loss)
    t0 = time.perf_counter()
    if isinstance(method, str):
        method = optimiser_for(method, maxiter=maxiter, learning_rate=learning_rate, tol=tol,
                               de_options=de_options)
    from tqdm.auto import tqdm

    with tqdm(total=method.budget, desc=f"calibrate ({method.name})", unit="iteration",
              disable=not progress) as bar:
        sol = method.minimise(obj, jac=jac, seed=seed, verbose=verbose, bar=bar)
        bar.total = bar.n  # a run that converged before its budget ends at 100 %
    wall = time.perf_counter() - t0

    z, theta = sol.z, sol.theta
    if not np.all(np.isfinite(theta)):
        raise CalibrationError(f"fit ({name}) diverged: non-finite parameters "
                               f"{dict(zip([p.name for p in params], theta.tolist()))}")
    fitted = with_theta(model, params, jnp.asarray(theta))
    r = np.asarray(obj.fn("resid_z")(jnp.asarray(z)))
    final = float(np.sum(r * r))
    if not math.isfinite(final):
        raise CalibrationError(f"fit ({name}) diverged: the loss at the returned parameters "
                               "is not finite")
    pred = obj.prediction_from_residuals(r)
    metrics = {k: error_metrics(obj.meas[k], pred[k]) for k in obj.meas}
    res = CalibrationResult(
        model=fitted, params={p.name: float(t) for p, t in zip(params, theta)},
        initial={p.name: p.init for p in params}, loss=final, history=sol.progress.history,
        n_evals=sol.progress.n_evals, n_grads=sol.progress.n_grads, wall_s=wall, method=name,
        metrics=metrics, e_rms=max(m[0] for m in metrics.values()),
        e_m=max(m[1] for m in metrics.values()), prediction=pred, message=sol.message,
        objective=obj,
    )
    if curvature:
        (res.curvature, res.covariance, res.std, res.rel_std,
         res.flat) = _curvature(obj, z, params, theta, final, flat_threshold, jac)
    return _unloaded(res) if payload is not None else res


def _loaded(model, data, payload):
    """``model`` with the measurements' payload law (:class:`~.predictors.Loaded`)."""
    from ..models.cone import Model
    from ..payloads import PayloadLaw
    from .predictors import Loaded

    if not isinstance(model, Model) or not isinstance(data, FrequencyResponse):
        raise CalibrationError("payload= is for a cone model (jaxdea.load_config) fitted to a "
                               "frequency response")
    if not isinstance(payload, PayloadLaw):
        raise CalibrationError(f"payload must be a payload law (jaxdea.Drag, ...), got "
                               f"{type(payload).__name__}")
    return Loaded(model, payload.with_mass(0.0))


def _unloaded(res: CalibrationResult) -> CalibrationResult:
    """The result of a fit with a payload law: ``model`` the cone model, ``payload`` the
    fitted law, and the names as given (``"actuator..."``, ``"payload.<name>"``)."""
    back = {v: k for k, v in res.model.parameter_aliases.items()}

    def name(n: str) -> str:
        return back.get(n, n[len("model."):] if n.startswith("model.") else n)

    res.model, res.payload = res.model.model, res.model.payload
    for attr in ("params", "initial", "std", "rel_std"):
        setattr(res, attr, {name(k): v for k, v in getattr(res, attr).items()})
    res.flat = [name(n) for n in res.flat]
    return res
