"""Predictors: ``predict(model, data) -> {channel: array}``, the model's output at the rows
or times of measured data, differentiable in the model's parameters.

:func:`frequency_response` for cone models (``jaxdea.Model``) and frequency-response data,
:func:`transient_predictor` for the viscoelastic models under a known drive and time-series
data; :func:`default_predict` picks one (other model families register in :data:`PREDICTORS`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError, DataError
from ..models.cone import Model
from ..payloads import PayloadLaw
from ..solver import LawsonRK4, SemilinearTerm
from ..studies import transient as ve
from ..studies.loadings import make_loadings
from .data import FrequencyResponse, TimeSeries

__all__ = ["PREDICTORS", "Loaded", "default_predict", "frequency_response",
           "transient_predictor"]


class Loaded(eqx.Module):
    """A cone model and the payload law its measurements were taken with: what
    :func:`jaxdea.calibrate` fits when given ``payload=``, so that the law's parameters are
    fitted like the model's (named ``"payload.<name>"``).

    **Arguments:**

    - `model`: the cone :class:`~jaxdea.Model`.
    - `payload`: the payload law (its mass: the data's ``mass`` column; set to 0 here).
    """

    model: Model
    payload: PayloadLaw

    @property
    def parameter_aliases(self) -> dict[str, str]:
        """``"payload.<name>"`` -> the law parameter's full path (in a sum of laws:
        ``"payload.parts.<i>.<name>"``)."""
        out = {}
        for i, law in enumerate(self.payload.laws):
            base = "payload" if len(self.payload.laws) == 1 else f"payload.parts.{i}"
            for f in dataclasses.fields(law):
                if f.name != "mass":
                    out[f"payload.{f.name}"] = f"{base}.{f.name}"
        return out


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

    **Arguments:**

    - `model`: a cone model (``jaxdea.Model``), or a :class:`Loaded` model with the payload
      law of the measurements (then the data's ``damping`` column is not used); its
      parameters may be traced.
    - `data`: the frequency response whose rows (``f``, ``mass``, ``damping``) to compute.
    - `cycles`: drive periods from rest per row.
    - `average`: last periods over which the metrics are taken (``1 <= average <= cycles``).
    - `dt_max`: largest step (s) when ``points_per_cycle`` is not given.
    - `points_per_cycle`: steps per drive period (at least 8).

    **Returns:**

    ``{"amplitude": m, "P_out": W}``, one value per row of ``data``.
    """
    if not (1 <= average <= cycles):
        raise CalibrationError(f"need 1 <= average <= cycles, got {average}, {cycles}")
    f = np.asarray(data.f, dtype=float)
    if points_per_cycle is None:
        points_per_cycle = int(2 * math.ceil(1.0 / (float(f.min()) * dt_max) / 2.0))
    ppc = max(int(points_per_cycle), 8)
    payload = None
    if isinstance(model, Loaded):
        model, payload = model.model, model.payload.with_mass(0.0)
    act = model.actuator
    loadings = make_loadings(model, data.mass, None if payload is not None else data.damping,
                             f, payload=payload)
    solver = LawsonRK4()
    term = SemilinearTerm(act.vector_field, act.linearisation)
    start = (cycles - average) * ppc

    def one(loading):
        y0 = act.initial_state(loading.payload)  # with a weight or a preload: per row
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
    """A predictor for the viscoelastic models (mass cone of papers 001/002, planar DEA of
    004) under a known drive.

    The drive's kink times (and the fixed step grid) are computed eagerly, so the predictor
    can run inside the fit's ``jit``/``vmap``. The data's ``voltage`` column must match
    ``signal`` to ``voltage_tol`` of its range (else :class:`~jaxdea.DataError`): the model is
    driven by ``signal``, not by the sampled voltage.

    **Arguments:**

    - `signal`: the drive that produced the data (e.g. paper 002's eq-25
      :class:`~jaxdea.signals.MultiSine`).
    - `fixed_steps`: integrate on that many uniform steps (plus kinks and sample times), for
      gradients that match finite differences; default the adaptive controller.
    - `voltage_tol`: allowed mismatch between the data's voltage and ``signal``, as a
      fraction of the voltage's range.
    - `solve_kwargs`: ``rtol``, ``atol``, ``max_steps`` of
      :func:`jaxdea.studies.transient.solve` (with ``fixed_steps``: ``rtol``, ``atol``).

    **Returns:**

    ``predict(model, data) -> {"displacement": m}`` at ``data.t`` (a
    :class:`~jaxdea.calibration.TimeSeries`). Used by the mass-cone recovery test (problem (a)
    of issue 5).
    """
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
            kw = dict(rtol=1e-8, atol=1e-10) | solve_kwargs
            disp = ve.displacement(model, signal, ts, rtol=kw["rtol"], atol=kw["atol"],
                                   fixed_steps=int(fixed_steps))
        else:
            disp = ve.displacement(model, signal, ts, **solve_kwargs)
        return {"displacement": disp}

    return predict


#: ``(model class, data class) -> predict``; other model families register here.
PREDICTORS: dict[tuple[type, type], Callable] = {}


def default_predict(model, data) -> Callable:
    """The predictor registered for this model and data kind (see :data:`PREDICTORS`).

    **Arguments:**

    - `model`: the model to fit.
    - `data`: the measured data.

    **Returns:**

    :func:`frequency_response` for a cone model and a frequency response, else the
    registered ``predict(model, data)``; :class:`~jaxdea.CalibrationError` if there is none.
    """
    if isinstance(data, FrequencyResponse) and isinstance(model, (Model, Loaded)):
        return frequency_response
    for (mcls, dcls), fn in PREDICTORS.items():
        if isinstance(model, mcls) and isinstance(data, dcls):
            return fn
    raise CalibrationError(f"no predictor for a {type(model).__name__} model and "
                           f"{type(data).__name__} data: pass predict=f(model, data) -> "
                           "{channel: array}")
