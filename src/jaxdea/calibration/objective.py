"""The objective of a fit: weighted residuals per channel, the loss, and their compiled
derivatives in the box space ``u`` and the unconstrained space ``z`` of the parameters.

Residuals are per channel and each channel has the same total weight: ``loss = mean_c mean_i
r_ci^2`` with ``r = (model - data) / range(data)`` (``"mse"``), ``r = model / data - 1``
(``"relative"``) or ``r = log(model / data)`` (``"log"``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError, DataError
from ..params import Param, with_theta

__all__ = ["LOSSES", "Objective", "ParameterSpace"]

LOSSES = ("mse", "relative", "log")


class ParameterSpace:
    """The three spaces of fitted parameters ``params`` (a list of
    :class:`~jaxdea.params.Param`): theta (their units), u (the box: log or linear) and z
    (unconstrained). What the optimisers of :mod:`.optimisers` read of an objective besides
    its loss: :class:`Objective` and any other objective (e.g.
    :class:`jaxdea.reproduce.ClaimsObjective`) share it."""

    params: list[Param]

    def u_of_z(self, z):
        """Box values of a point in z (traceable)."""
        return jnp.stack([p.u_of_z(z[i]) for i, p in enumerate(self.params)])

    def z0(self) -> np.ndarray:
        """The start values in z."""
        return np.array([p.z_of_u(float(p.u_of_theta(p.init))) for p in self.params])

    def theta_of_z(self, z) -> np.ndarray:
        """Parameter values (their units) of a point in z."""
        u = np.asarray(self.u_of_z(jnp.asarray(z)))
        return np.array([float(p.theta_of_u(u[i])) for i, p in enumerate(self.params)])

    def theta_of_u(self, u) -> np.ndarray:
        """Parameter values (their units) of a point in u."""
        return np.array([float(p.theta_of_u(u[i])) for i, p in enumerate(self.params)])


class Objective(ParameterSpace):
    """Residuals, loss and derivatives of a fit in u (box) and z (unconstrained) space.

    **Arguments:**

    - `model`: the model at the start values.
    - `data`: the measured data (its ``channels`` are fitted).
    - `params`: the fitted parameters (:func:`~jaxdea.calibration.make_params`).
    - `predict`: ``predict(model, data) -> {channel: array}``.
    - `loss`: ``"mse"``, ``"relative"`` or ``"log"`` (see :mod:`jaxdea.calibration.fit`).

    The compiled pieces (:meth:`fn`) are built on first use and kept.
    """

    def __init__(self, model, data, params: list[Param], predict: Callable, loss: str):
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
            pred = predict(with_theta(model, params, theta), data)
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

        self.residual_u = residual_u
        self.residual_z = lambda z: residual_u(self.u_of_z(z))
        self._cache: dict[str, Callable] = {}

    def __getstate__(self) -> dict:
        """Pickled without its compiled pieces (a Dask worker builds its own, once)."""
        state = dict(self.__dict__)
        state["_cache"] = {}
        return state

    def fn(self, name: str) -> Callable:
        """A compiled piece, built on first use: ``"resid_z"`` (residuals of z), ``"jac_z"`` /
        ``"jacrev_z"`` (``(J, r)`` by forward / reverse mode), ``"vg_z"`` (loss and gradient),
        ``"loss_u_batch"`` (losses of a batch of u) or ``"du_dz"``."""
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

    def jacobian(self, z, jac: str):
        """``(J, r)``: residual Jacobian in z and the residuals, by ``jac`` mode."""
        return self.fn("jac_z" if jac == "fwd" else "jacrev_z")(jnp.asarray(z))

    def value_and_grad(self, z, jac: str):
        """``(loss, gradient)`` at z, the gradient by ``jac`` mode (``"fwd"``: from J)."""
        z = jnp.asarray(z, dtype=jnp.float64)
        if jac == "fwd":
            J, r = self.fn("jac_z")(z)
            return float(jnp.sum(r * r)), np.asarray(2.0 * (J.T @ r))
        v, g = self.fn("vg_z")(z)
        return float(v), np.asarray(g)
