"""The optimisers of a fit, as small objects carrying their own settings.

Each optimiser minimises an :class:`~jaxdea.calibration.objective.Objective` with
:meth:`AbstractOptimiser.minimise` and returns a :class:`Solution`:

- :class:`LBFGS`: scipy's L-BFGS-B (Fortran, Moré-Thuente-type line search) on ``z`` with the
  exact JAX gradient. Chosen over ``optax.lbfgs`` because its line search runs on the host,
  so the model's value-and-gradient is compiled once (the optax zoom line search traces the
  model a second time inside its ``while_loop``) and every model evaluation is counted.
- :class:`Adam`: ``optax.adam`` on ``z``.
- :class:`LM`: scipy's ``least_squares`` (trust-region reflective) with the JAX Jacobian: a
  Gauss-Newton method, natural for these least-squares fits.
- :class:`DE`: scipy's ``differential_evolution`` with a *vectorized* objective: each
  generation (the whole population) is one ``jax.vmap``-ed, jitted model call, searching the
  box ``[ulo, uhi]``. Defaults are paper 001's settings (:data:`DE_PAPER`).

``calibrate(..., method="lbfgs" | "adam" | "lm" | "de")`` builds one with
:func:`optimiser_for`.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError
from .objective import Objective

__all__ = ["DE", "DE_PAPER", "LBFGS", "LM", "METHODS", "OPTIMISERS", "AbstractOptimiser",
           "Adam", "Progress", "Solution", "optimiser_for"]

#: Paper 001 (Sec 4.2) differential-evolution settings.
DE_PAPER = dict(popsize=240, maxiter=115, mutation=0.6, recombination=0.9,
                strategy="rand1bin")


@dataclass
class Progress:
    """What a run has done so far."""

    n_evals: int = 0  #: model evaluations (a DE population counts as its size)
    n_grads: int = 0  #: of which with a gradient
    history: list[float] = field(default_factory=list)  #: loss per iteration / generation
    #: a progress bar (``tqdm``-like) advanced by :meth:`record`, or None
    bar: Any = field(default=None, repr=False, compare=False)

    def record(self, loss: float) -> None:
        """One iteration (generation) done with ``loss``: kept in :attr:`history`, and the
        bar moves on showing it."""
        self.history.append(loss)
        if self.bar is not None:
            self.bar.set_postfix_str(f"loss {loss:.6g}", refresh=False)
            self.bar.update(1)


@dataclass(frozen=True)
class Solution:
    """What :meth:`AbstractOptimiser.minimise` returns."""

    z: np.ndarray  #: the parameters in the unconstrained space
    theta: np.ndarray  #: the parameters in their units
    message: str  #: the optimiser's stopping message
    progress: Progress


class AbstractOptimiser(abc.ABC):
    """An optimiser: its settings are its fields; :meth:`minimise` runs it."""

    #: the name in ``calibrate(method=...)``, results and messages
    name: ClassVar[str]
    #: True: searches the box of the bounds, which must then be finite
    searches_box: ClassVar[bool] = False

    @property
    def budget(self) -> int:
        """Most iterations (generations, evaluations): the length of a progress bar."""
        return int(getattr(self, "maxiter"))

    @abc.abstractmethod
    def minimise(self, obj: Objective, *, jac: str, seed: int = 0,
                 verbose: bool = False, bar=None) -> Solution:
        """Minimise the loss of ``obj``.

        **Arguments:**

        - `obj`: the objective.
        - `jac`: ``"fwd"`` or ``"rev"``: how derivatives are taken.
        - `seed`: random seed (stochastic optimisers).
        - `verbose`: print progress.
        - `bar`: a progress bar (``tqdm``-like), advanced once per :attr:`budget` unit.

        **Returns:**

        A :class:`Solution`. Raises :class:`~jaxdea.CalibrationError` if the fit diverges.
        """


def _diverged(method: str, k: int, what: str, obj: Objective, z, hint: str) -> CalibrationError:
    try:
        theta = obj.theta_of_z(z)
        at = ", ".join(f"{p.name} = {t:.4g}" for p, t in zip(obj.params, theta))
    except Exception:  # noqa: BLE001
        at = "unknown"
    return CalibrationError(f"fit diverged ({method}, evaluation {k}): {what} at {at}; {hint}")


@dataclass(frozen=True)
class LBFGS(AbstractOptimiser):
    """scipy's L-BFGS-B on the unconstrained parameters, with the JAX gradient.

    **Arguments:**

    - `maxiter`: iterations (model evaluations at most ``10 * maxiter``).
    - `tol`: scipy's ``ftol``, relative to the starting loss.
    - `maxcor`: stored correction pairs.
    """

    maxiter: int = 200
    tol: float = 1e-10
    maxcor: int = 20
    name: ClassVar[str] = "lbfgs"

    @property
    def budget(self) -> int:
        return int(self.maxiter) + 1  # the start, then each iteration

    def minimise(self, obj: Objective, *, jac: str, seed: int = 0,
                 verbose: bool = False, bar=None) -> Solution:
        from scipy.optimize import minimize

        state = Progress(bar=bar)
        maxiter = self.maxiter
        z0 = obj.z0()
        f0, g0 = obj.value_and_grad(z0, jac)
        state.n_evals += 1
        state.n_grads += 1
        if not (math.isfinite(f0) and np.all(np.isfinite(g0))):
            raise _diverged("lbfgs", 1, f"loss = {f0} / non-finite gradient at the start", obj,
                            z0, "check the start values and the data")
        state.record(f0)
        # scipy sees the loss relative to the start: its ftol (absolute below 1) is then relative
        scale = abs(f0) if f0 != 0 else 1.0
        penalty = 1e6
        bad = {"run": 0, "last_g": g0 / scale}

        def fg(z):
            f, g = obj.value_and_grad(z, jac)
            state.n_evals += 1
            state.n_grads += 1
            if not (math.isfinite(f) and np.all(np.isfinite(g))):
                bad["run"] += 1
                if bad["run"] >= 20:
                    raise _diverged("lbfgs", state.n_evals, f"loss = {f} on 20 evaluations "
                                    "in a row", obj, z, "tighten the bounds")
                return penalty, -bad["last_g"]  # a wall: the line search backs off
            bad["run"], bad["last_g"] = 0, g / scale
            return f / scale, g / scale

        def cb(intermediate_result):
            state.record(float(intermediate_result.fun) * scale)
            if verbose:
                print(f"lbfgs it {len(state.history) - 1}: loss {state.history[-1]:.6g}")

        res = minimize(fg, z0, jac=True, method="L-BFGS-B", callback=cb,
                       options=dict(maxiter=maxiter, maxfun=10 * maxiter, ftol=self.tol,
                                    gtol=1e-14, maxcor=self.maxcor))
        if not res.fun < penalty:
            raise _diverged("lbfgs", state.n_evals, "no finite loss after the start", obj,
                            res.x, "tighten the bounds")
        return Solution(res.x, obj.theta_of_z(res.x), str(res.message), state)


@dataclass(frozen=True)
class Adam(AbstractOptimiser):
    """``optax.adam`` on the unconstrained parameters; returns the best iterate.

    **Arguments:**

    - `learning_rate`: Adam's step in z.
    - `maxiter`: steps at most.
    - `tol`: a step improves on the best loss if it is below ``best * (1 - tol)``.
    - `patience`: stop after this many steps without improvement.
    """

    learning_rate: float = 0.05
    maxiter: int = 2000
    tol: float = 1e-10
    patience: int = 100
    name: ClassVar[str] = "adam"

    def minimise(self, obj: Objective, *, jac: str, seed: int = 0,
                 verbose: bool = False, bar=None) -> Solution:
        import optax

        state = Progress(bar=bar)
        lr, tol = self.learning_rate, self.tol
        opt = optax.adam(lr)
        z = jnp.asarray(obj.z0())
        st = opt.init(z)
        best = (math.inf, np.asarray(z))
        stall = 0
        for k in range(self.maxiter):
            f, g = obj.value_and_grad(z, jac)
            state.n_evals += 1
            state.n_grads += 1
            if not (math.isfinite(f) and np.all(np.isfinite(g))):
                raise _diverged("adam", state.n_evals, f"loss = {f}", obj, z,
                                f"lower learning_rate (now {lr:g}) or tighten the bounds")
            state.record(f)
            if f < best[0] * (1 - tol):
                stall = 0
            else:
                stall += 1
            if f < best[0]:
                best = (f, np.asarray(z))
            if stall >= self.patience:
                break
            if verbose and k % 50 == 0:
                print(f"adam step {k}: loss {f:.6g}")
            upd, st = opt.update(jnp.asarray(g), st, z)
            z = optax.apply_updates(z, upd)
        message = f"adam: {len(state.history)} steps, best loss {best[0]:.4g}"
        return Solution(best[1], obj.theta_of_z(best[1]), message, state)


@dataclass(frozen=True)
class LM(AbstractOptimiser):
    """Gauss-Newton / Levenberg-Marquardt: scipy's ``least_squares`` (trust-region
    reflective) on the residuals, with the JAX Jacobian.

    **Arguments:**

    - `maxiter`: residual evaluations at most (``max_nfev``).
    - `tol`: ``ftol`` (at least 1e-15).
    """

    maxiter: int = 100
    tol: float = 1e-10
    name: ClassVar[str] = "lm"

    def minimise(self, obj: Objective, *, jac: str, seed: int = 0,
                 verbose: bool = False, bar=None) -> Solution:
        from scipy.optimize import least_squares

        state = Progress(bar=bar)
        cache = {}
        bad = {"run": 0}

        def both(z):
            key = np.asarray(z).tobytes()
            if key not in cache:
                J, r = obj.jacobian(z, jac)
                state.n_evals += 1
                state.n_grads += 1
                r, J = np.asarray(r), np.asarray(J)
                if np.all(np.isfinite(r)) and np.all(np.isfinite(J)):
                    bad["run"] = 0
                else:  # trust-region reflective shrinks its radius on a non-finite trial
                    bad["run"] += 1
                    if bad["run"] >= 20:
                        raise _diverged("lm", state.n_evals, "non-finite residuals on 20 "
                                        "evaluations in a row", obj, z, "tighten the bounds")
                    J = np.nan_to_num(J)
                cache.clear()
                cache[key] = (r, J)
                state.record(float(r @ r))
            return cache[key]

        res = least_squares(lambda z: both(z)[0], obj.z0(), jac=lambda z: both(z)[1],
                            method="trf", x_scale="jac", max_nfev=self.maxiter,
                            ftol=max(self.tol, 1e-15), xtol=1e-12, gtol=1e-15)
        if not np.all(np.isfinite(res.fun)):
            raise _diverged("lm", state.n_evals, "non-finite residuals at the end", obj,
                            res.x, "tighten the bounds")
        return Solution(res.x, obj.theta_of_z(res.x), str(res.message), state)


@dataclass(frozen=True)
class DE(AbstractOptimiser):
    """Differential evolution (scipy, vectorized: one ``vmap``-ed model call per generation)
    over the box of the bounds (uniform in log for log parameters); no polishing.

    **Arguments:** (defaults: paper 001, :data:`DE_PAPER`)

    - `population`: members (at least 5).
    - `generations`: generations at most (scipy's ``maxiter``).
    - `mutation`: F, or a ``(min, max)`` dithering range.
    - `recombination`: crossover probability CR.
    - `strategy`: scipy's strategy name (classic DE/rand/1/bin).
    - `tol`, `atol`: scipy's convergence tolerances (0: run all generations).
    - `init`: scipy's ``init`` (an initial population in u, or a scheme name); default a
      Latin hypercube of ``population`` members drawn with the fit's seed.
    - `client`: a ``dask.distributed.Client``: each generation's population is evaluated as
      ``slices`` tasks on its workers (the objective is sent once per worker and compiled
      there once); default: in this process.
    - `slices`: population slices per generation with a client (default: 2 per worker).
    """

    population: int = DE_PAPER["popsize"]
    generations: int = DE_PAPER["maxiter"]
    mutation: Any = DE_PAPER["mutation"]
    recombination: float = DE_PAPER["recombination"]
    strategy: str = DE_PAPER["strategy"]
    tol: float = 0.0
    atol: float = 0.0
    init: Any = field(default=None, compare=False)
    client: Any = field(default=None, compare=False, repr=False)
    slices: int | None = None
    name: ClassVar[str] = "de"
    searches_box: ClassVar[bool] = True

    @property
    def budget(self) -> int:
        return int(self.generations)

    def __post_init__(self):
        pop = int(self.population)
        if pop < 5:
            raise CalibrationError(f"DE population {pop} too small: need >= 5")

    @classmethod
    def from_options(cls, de_options: dict | None = None, maxiter: int | None = None) -> DE:
        """The DE of ``calibrate(method="de", de_options=..., maxiter=...)``.

        **Arguments:**

        - `de_options`: overrides of :data:`DE_PAPER` (scipy's names: ``popsize``,
          ``maxiter``, ``mutation``, ``recombination``, ``strategy``) and of ``tol``,
          ``atol``, ``init``.
        - `maxiter`: generations; overrides ``de_options["maxiter"]``.

        **Returns:**

        The :class:`DE`; :class:`~jaxdea.CalibrationError` on an unknown option.
        """
        o = dict(DE_PAPER)
        o.update(tol=0.0, atol=0.0)
        de_options = de_options or {}
        unknown = sorted(set(de_options) - set(o) - {"init"})
        if unknown:
            raise CalibrationError(f"unknown de_options {', '.join(unknown)}; allowed: "
                                   f"{', '.join([*o, 'init'])}")
        o.update(de_options)
        if maxiter is not None:
            o["maxiter"] = maxiter
        return cls(population=int(o["popsize"]), generations=o["maxiter"],
                   mutation=o["mutation"], recombination=o["recombination"],
                   strategy=o["strategy"], tol=o["tol"], atol=o["atol"], init=o.get("init"))

    def minimise(self, obj: Objective, *, jac: str = "fwd", seed: int = 0,
                 verbose: bool = False, bar=None) -> Solution:
        from scipy.optimize import differential_evolution
        from scipy.stats import qmc

        state = Progress(bar=bar)
        lo = np.array([p.ulo for p in obj.params])
        hi = np.array([p.uhi for p in obj.params])
        n = len(obj.params)
        pop = int(self.population)
        init = self.init
        if init is None:
            init = qmc.scale(qmc.LatinHypercube(d=n, rng=np.random.default_rng(seed))
                             .random(pop), lo, hi)
        batch = obj.fn("loss_u_batch") if self.client is None else _on_cluster(
            self.client, obj, self.slices)

        def f(x):  # x: (n, S) -> (S,)
            vals = np.asarray(batch(jnp.asarray(x.T)))
            state.n_evals += x.shape[1]
            return np.where(np.isfinite(vals), vals, np.inf)

        def cb(intermediate_result):
            state.record(float(intermediate_result.fun))
            if verbose:
                print(f"de generation {len(state.history)}: best loss "
                      f"{intermediate_result.fun:.6g}")

        res = differential_evolution(
            f, list(zip(lo, hi)), init=init, vectorized=True, updating="deferred",
            polish=False, rng=np.random.default_rng(seed), callback=cb,
            maxiter=self.generations, mutation=self.mutation,
            recombination=self.recombination, strategy=self.strategy, tol=self.tol,
            atol=self.atol)
        if not np.isfinite(res.fun):
            raise CalibrationError("fit diverged (de): no member of the population had a "
                                   "finite loss; check bounds and data")
        z = np.array([p.z_of_u(float(u)) for p, u in zip(obj.params, res.x)])
        return Solution(z, obj.theta_of_u(res.x), str(res.message), state)


def _population_slice(obj: Objective, u: np.ndarray) -> np.ndarray:
    """The losses of population members ``u`` (S, n) on a Dask worker (``obj`` is that
    worker's one copy of the objective: its compiled loss is kept between generations)."""
    return np.asarray(obj.fn("loss_u_batch")(jnp.asarray(u)))


def _on_cluster(client, obj: Objective, slices: int | None) -> Callable:
    """``u (S, n) -> losses (S,)`` evaluated as equal slices (the last padded by repeating
    its last member), one task each, on the workers of ``client``."""
    from ..studies.distributed import check_client, padded_cells

    try:
        n_workers = check_client(client)
    except Exception as exc:  # noqa: BLE001 - a SweepError; calibration reports its own type
        raise CalibrationError(str(exc)) from None
    k = int(slices or 2 * n_workers)
    if k < 1:
        raise CalibrationError(f"DE slices must be >= 1, got {slices!r}")
    remote = client.scatter(obj, broadcast=True)  # once per worker, kept there

    def batch(u):
        u = np.asarray(u)
        size = -(-u.shape[0] // k)
        parts = [u[padded_cells(lo, size, u.shape[0])] for lo in range(0, u.shape[0], size)]
        futures = client.map(_population_slice, [remote] * len(parts), parts, pure=False)
        return np.concatenate(client.gather(futures))[:u.shape[0]]

    return batch


#: ``calibrate``'s method names and their optimisers.
OPTIMISERS: dict[str, type[AbstractOptimiser]] = {"lbfgs": LBFGS, "adam": Adam, "de": DE,
                                                  "lm": LM}
METHODS = tuple(OPTIMISERS)


def optimiser_for(method: str, *, maxiter: int | None = None, learning_rate: float = 0.05,
                  tol: float = 1e-10, de_options: dict | None = None) -> AbstractOptimiser:
    """The optimiser of ``calibrate(method=..., maxiter=..., ...)``.

    **Arguments:**

    - `method`: ``"lbfgs"``, ``"adam"``, ``"lm"`` or ``"de"``.
    - `maxiter`: iterations (generations for DE); default 200 / 2000 / 100 / 115 for
      lbfgs / adam / lm / de.
    - `learning_rate`: Adam's step.
    - `tol`: the tolerance of lbfgs, adam and lm.
    - `de_options`: DE settings by scipy's names (see :meth:`DE.from_options`).

    **Returns:**

    The :class:`AbstractOptimiser`.
    """
    if method == "lbfgs":
        return LBFGS(maxiter=maxiter or 200, tol=tol)
    if method == "adam":
        return Adam(learning_rate=learning_rate, maxiter=maxiter or 2000, tol=tol)
    if method == "lm":
        return LM(maxiter=maxiter or 100, tol=tol)
    if method == "de":
        return DE.from_options(de_options, maxiter)
    raise CalibrationError(f"method = {method!r} must be one of {', '.join(METHODS)}")
