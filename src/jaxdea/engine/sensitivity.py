"""Implicit derivatives of periodic steady states: d(metrics)/d(parameters) at the orbit.

A batch of designs (parameter vectors ``theta``, ``(K, n)``) each runs a batch of cells (a
drive frequency, payload, phase per cell) through ``build(theta) -> (actuator, loadings)``.
For every cell the periodic orbit ``y* = Phi_T(y*, theta)`` is found as in
:func:`jaxdea.engine.periodic.periodic_cells` (settle from rest or from given states, then
Newton shooting), and its metrics ``m = (P_out, P_in, efficiency, amplitude)`` over one
period from ``y*`` are differentiated implicitly:

    dy*/dtheta = (I - dPhi/dy)^-1 dPhi/dtheta,    dm/dtheta = dm/dtheta|_y + dm/dy dy*/dtheta,

with ``dPhi/dy``, ``dPhi/dtheta``, ``dm/dy`` and ``dm/dtheta`` from forward mode through one
period of the lane engine, tangents over the d dynamical states and the n parameters (one
``jax.jacfwd`` on several devices, one pass per direction on one: :func:`jacobian_by_columns`;
cells are independent, so the same perturbation of every cell gives each cell its own
Jacobian). The Newton pass that confirms convergence is that same pass.
Nothing differentiates through the settling or the Newton iterations: they run on the host.

:func:`implicit` wraps a host-side solver ``theta -> (values, jacobians)`` into a
``jax.custom_jvp`` function: forward mode uses the Jacobians, and ``jax.grad`` /
``jax.jacrev`` work by JAX's transposition of that linear tangent rule. :func:`steady_metrics`
is the one-design case. The parameters must be concrete (the solver runs on the host): these
functions work under ``jax.grad``, ``jax.jacfwd`` and ``jax.jacrev``, not under ``jax.jit``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.cone import ConeState
from .batch import driven_membranes
from .implicit import implicit
from .lane_state import rest_states, scatter_each
from .lanes import run_protocol
from .periodic import (
    STABLE_MULTIPLIER,
    flatten_dynamical,
    newton_step,
    radius_above,
    solve_cells,
    step_residual,
    with_dynamical,
)
from .sharding import cell_sharded
from .step_control import StepControl

#: The differentiated metrics of a cell, in this order.
METRICS = ("P_out", "P_in", "efficiency", "amplitude")


@dataclasses.dataclass(frozen=True)
class Steady:
    """Settings of the periodic solve behind the derivatives.

    **Arguments:**

    - `tol`: Newton tolerance on the scaled state (:func:`periodicity_residual`); the
      derivatives are those at an orbit this close to periodic.
    - `warmup`: most cycles of the settling stage.
    - `newton`: most Newton iterations after it.
    - `control`: step policy of the lane engine (tight: finite differences and the implicit
      derivative agree to ~1e-4 only when the adaptive steps resolve the orbit well).
    - `lanes`: lane pool per design.
    """

    tol: float = 1e-10
    warmup: int = 30
    newton: int = 10
    control: StepControl = StepControl(rtol=1e-9, dt_max=2e-4)
    lanes: int = 16


class SteadyResult(NamedTuple):
    """Converged orbits of a batch of designs x cells (numpy arrays, leading axes (K, C))."""

    values: np.ndarray  #: (K, C, 4) metrics (:data:`METRICS`); NaN where status != 0
    jac: np.ndarray | None  #: (K, C, 4, n) d metrics / d theta; None unless asked
    status: np.ndarray  #: (K, C) 0 = ok, else :data:`jaxdea.STATUS`
    state: ConeState  #: (K, C, ...) the state y* at the start of the converged period
    residual: np.ndarray  #: (K, C) last Newton step (scaled), or the settling residual

    def converged_states(self) -> ConeState:
        """:attr:`state` where status is 0, NaN elsewhere: start states for a continuation
        (:func:`solve_designs` starts a NaN cell from rest)."""
        ok = self.status == 0
        return jax.tree_util.tree_map(
            lambda a: np.where(ok.reshape(ok.shape + (1,) * (np.ndim(a) - 2)), a, np.nan),
            self.state)


def _metric_stack(res) -> jax.Array:
    return jnp.stack([getattr(res, k) for k in METRICS], axis=-1)


def _settle(actuator, loadings, initial, *, warmup, tol, control, lanes, driven):
    """Settle every design's cells (leading axis: designs) from ``initial``.

    It takes the built models (:func:`_built`), not ``build`` and ``theta``, and always
    explicit start states: one compiled program then serves every parameterisation of the
    same model (a :class:`Sub` build and the full one, any parameter
    names) and every start (rest or a continuation). Measured: ``docs/performance.md``."""
    def one(act, ld, y0):
        return run_protocol(act, ld, cycles=warmup, average=1, settle=tol, control=control,
                            lanes=lanes, initial=y0, driven=driven)

    return jax.vmap(one)(actuator, loadings, initial)


@eqx.filter_jit
def _built(build, theta):
    """Every design's ``(actuator, loadings)`` and the rest state of its cells (leaves
    ``(K, ...)`` and ``(K, C, ...)``): what :func:`_settle` runs."""
    def one(b, th):
        act, ld = b(th)
        return act, ld, rest_states(act, ld)

    return jax.vmap(one)(build, theta)


def jacobian_by_columns(f, z0: jax.Array, order: jax.Array | None = None,
                        count: jax.Array | None = None):
    """``jax.jacfwd(f, has_aux=True)(z0)`` computed as one ``jax.jvp`` per basis direction,
    in sequence (a ``fori_loop``), instead of with the m tangents batched.

    ``f`` runs the lane engine (a ``while_loop`` of adaptive steps). Compiled for one
    device under the ``vmap`` over designs of :func:`_shoot`, that loop with a batch of
    tangents is far slower than the batch's size times one tangent, and this is the faster:
    17 designs x 8 cells, m = 14: 1.2-1.3 s against ``jacfwd``'s 5.5-5.8 s (two tangents at a
    time: 11.7 s), compiled in 17 s against 32 s; 8 designs, m = 9: 0.46 s against 1.6 s.
    The compiled program with ``jacfwd`` is twice the size of the same program split over
    two devices (``shard_map``: 15.7 k multiplies against 5.5 k per device), and split over
    two devices ``jacfwd`` is the faster: 0.12 s against 0.27 s (same Jacobian to 1e-11). So
    :func:`_stages` uses this on one device and ``jacfwd`` on several; a power map's shoot
    (:func:`jaxdea.engine.periodic.shoot_period`, no vmap over designs, d = 5) keeps
    ``jacfwd`` on one device too: 1.0-1.2 s against 1.5-1.6 s on the periodic bench sweep.
    The adaptive steps follow the primal only, so each pass takes the same steps.

    **Arguments:**

    - `f`: ``z -> (out, aux)``, ``out`` a pytree of arrays.
    - `z0`: ``(m,)`` point of the derivative.
    - `order`, `count`: only the columns ``order[:count]`` (``(m,)`` integers, a scalar;
      both may be traced), one pass each in that order; the others are NaN. One compiled
      program then serves any set of columns (``count`` >= 1). Default: every column.

    **Returns:**

    ``(jac, aux)``: ``jac`` as ``out`` with a trailing axis of size m (as ``jax.jacfwd``),
    ``aux`` that of the first pass.
    """
    m = z0.shape[0]
    eye = jnp.eye(m, dtype=z0.dtype)
    if order is None:
        order, count = jnp.arange(m), m

    def column(e):
        _, tangent, aux = jax.jvp(f, (z0,), (e,), has_aux=True)
        return tangent, aux

    shapes = jax.eval_shape(column, eye[0])

    def body(i, carry):
        cols, aux = carry
        tangent, new = column(eye[order[i]])
        cols = scatter_each(cols, order[i], tangent)
        aux = jax.tree_util.tree_map(lambda a, b: jnp.where(i == 0, b, a), aux, new)
        return cols, aux

    cols = jax.tree_util.tree_map(lambda s: jnp.full((m,) + s.shape, jnp.nan, s.dtype),
                                  shapes[0])
    aux = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes[1])
    cols, aux = jax.lax.fori_loop(0, count, body, (cols, aux))
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), cols), aux


def _shoot(build, theta, y, active, order=None, count=None, *, params, control, lanes,
           driven):
    """One period of every active cell from ``y`` with the Jacobians of the end state and of
    the metrics with respect to the start state (and the parameters if ``params``), and the
    gap ``Phi_T(y) - y``. The Newton step is solved on the host
    (:func:`jaxdea.engine.periodic.newton_step`): a batched LAPACK solve inside a program
    split over devices can deadlock XLA's CPU thread pool.

    With ``order`` and ``count`` (one device): the Jacobians by :func:`jacobian_by_columns`,
    its columns ``order[:count]`` only (the states' and the parameters asked for; the others
    NaN), so that one program serves a solve with every parameter's derivative, with the
    peak search's shift only and with none. Without (several devices): ``jax.jacfwd``, every
    column."""

    def one(build, th, y, act):
        flat = flatten_dynamical(y)
        d, n = flat.shape[-1], th.shape[0]

        def period(z):
            actuator, ld = build(th + z[d:] if params else th)
            res = run_protocol(actuator, ld, cycles=1, average=1,
                               initial=with_dynamical(y, flat + z[:d]), active=act,
                               control=control, pools=(lanes,), driven=driven)
            out = (flatten_dynamical(res.final_state), _metric_stack(res))
            return out, res

        z0 = jnp.zeros(d + n if params else d, flat.dtype)
        (j_out, j_m), res = (jacobian_by_columns(period, z0, order, count)
                             if order is not None
                             else jax.jacfwd(period, has_aux=True)(z0))
        return res, j_out, j_m, flatten_dynamical(res.final_state) - flat

    return jax.vmap(one)(build, theta, y, active)


class Sub(eqx.Module):
    """``build`` with only the ``free`` entries of ``theta`` varied (the rest held): a
    solve on several devices that needs the derivatives in those parameters only."""

    build: Callable
    theta: jax.Array
    free: tuple = eqx.field(static=True)

    def __call__(self, sub):
        return self.build(self.theta.at[jnp.asarray(self.free)].set(sub))


def _columns(jac, n: int) -> tuple[int, ...]:
    """The parameter indices whose derivatives ``jac`` asks for (see :func:`solve_designs`)."""
    if jac is True or jac is False:
        return tuple(range(n)) if jac else ()
    free = tuple(sorted({int(i) for i in jac}))
    if not free or free[0] < 0 or free[-1] >= n:
        raise ValueError(f"jac: parameter indices in [0, {n}), got {jac!r}")
    return free


def _settle_split(_, actuator, loadings, initial, **static):
    return _settle(actuator, loadings, initial, **static)


def _shoot_split(_, build, theta, y, active, **static):
    return _shoot(build, theta, y, active, **static)


_SETTLE = eqx.filter_jit(_settle)
_SHOOT = eqx.filter_jit(_shoot)


def _stages(devices: tuple):
    """The settle and shoot stages over the design axis, split over ``devices`` (each device
    runs its own designs to the end; no collective) or on one device."""
    if len(devices) < 2:
        return (lambda a, ld, y0, **kw: _host(_SETTLE(a, ld, y0, **kw)),
                lambda b, th, y, a, **kw: _host(_SHOOT(b, th, y, a, **kw)))
    settle, shoot = cell_sharded(_settle_split, devices), cell_sharded(_shoot_split, devices)
    return (lambda a, ld, y0, **kw: settle(None, a, ld, y0, **kw),
            lambda b, th, y, a, **kw: shoot(None, b, th, y, a, **kw))


def _pad(tree, k: int):
    """``tree``'s leading (design) axis padded to ``k`` by repeating its last entry."""
    def pad(a):  # jnp for the build's arrays: they may be autodiff tracers (jax.grad)
        if k <= a.shape[0]:
            return a
        xp = np if isinstance(a, np.ndarray) else jnp
        return xp.concatenate([a, xp.repeat(a[-1:], k - a.shape[0], axis=0)])
    return jax.tree_util.tree_map(pad, tree)


def _host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def stack_designs(builds) -> Callable:
    """One build per design stacked into one (leading axis = designs) for
    :func:`solve_designs` ``(stacked=True)``: designs whose cells differ (e.g. frequencies)."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *builds)


def solve_designs(build: Callable, theta, *, settings: Steady = Steady(), initial=None,
                  jac: bool | tuple[int, ...] = True, stacked: bool = False,
                  devices: tuple | None = None) -> SteadyResult:
    """Periodic orbits, metrics and (optionally) their implicit derivatives.

    **Arguments:**

    - `build`: ``theta (n,) -> (actuator, loadings)`` with ``C`` cells; a pytree callable
      (an ``equinox.Module``), so that new values of its arrays do not recompile.
    - `theta`: ``(K, n)`` parameter vectors, one per design (concrete).
    - `settings`: :class:`Steady`.
    - `initial`: start states ``(K, C, ...)`` of the settling stage (default, and for
      cells whose start state is not finite: rest at the static equilibrium).
    - `jac`: also return ``d metrics / d theta`` (True), or only its columns of these
      parameter indices (the others NaN; e.g. the peak search's frequency shift).
    - `stacked`: ``build``'s arrays carry a leading design axis (:func:`stack_designs`);
      default: one build shared by every design.
    - `devices`: split the designs over these JAX devices (each runs its share to the end,
      with no collective; the design count is padded to a multiple of their number);
      default: one device.

    **Returns:**

    A :class:`SteadyResult`.
    """
    theta = np.asarray(theta, dtype=float)
    if theta.ndim != 2:
        raise ValueError(f"theta must be (designs, parameters), got shape {theta.shape}")
    s = settings
    k, n = theta.shape
    free = _columns(jac, n)
    devices = tuple(devices or jax.devices()[:1])
    if k < len(devices):
        devices = devices[:k]
    kp = -(-k // len(devices)) * len(devices)
    if not stacked:
        build = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (k,) + jnp.shape(a)),
                                       build)
    build, th = _pad(build, kp), _pad(theta, kp)
    # every design built once: the settling runs these models, and design 0's cells give
    # the driven membranes and the cell count
    actuators, loads, rest = _host(_built(build, jnp.asarray(th)))
    ld0 = jax.tree_util.tree_map(lambda a: a[0], loads)
    driven = driven_membranes(ld0)
    n_cells = int(ld0.drive.frequency.shape[0])
    lanes = int(min(n_cells, s.lanes))
    settle, shoot = _stages(devices)
    init = _with_rest(rest, None if initial is None else _pad(initial, kp))
    res = _trim(settle(actuators, loads, init, warmup=int(s.warmup), tol=float(s.tol),
                       control=s.control, lanes=lanes, driven=driven), k)
    status = np.asarray(res.status).copy()
    y = res.final_state
    residual = np.asarray(res.residual).copy()
    d = int(flatten_dynamical(y).shape[-1])
    if len(devices) < 2:
        # every shot is one program with the d + n columns, of which it computes the
        # states' and those of ``free`` (jacobian_by_columns): the same program for any jac
        rest_cols = [d + i for i in range(n) if i not in free]
        order = np.array(list(range(d)) + [d + i for i in free] + rest_cols)
        shot_build, shot_th = build, th
        columns = dict(order=jnp.asarray(order), count=jnp.asarray(d + len(free)), params=True)
        cols = [d + i for i in free]  # ``free``'s columns of the shot's Jacobians
    else:
        # jax.jacfwd computes every column of its tangent: only the parameters asked for
        sub = len(free) < n and bool(free)
        shot_build = Sub(build, jnp.asarray(th), free) if sub else build
        shot_th = th[:, list(free)] if sub else th
        columns = dict(params=bool(free))
        cols = [d + i for i in (range(len(free)) if sub else free)]
    values = np.full((k, n_cells, len(METRICS)), np.nan)
    jacs = np.full((k, n_cells, len(METRICS), n), np.nan) if free else None
    final = jax.tree_util.tree_map(np.array, y)
    # every cell that settled or needs shooting gets at least one Jacobian pass: it confirms
    # convergence and gives the derivatives at the same time
    pending = (status == 0) | (status == 4)
    status = np.where(pending, 4, status)
    stepped = np.zeros_like(pending)  # cells moved by a Newton step (off the trajectory)
    for _ in range(int(s.newton) + 1):
        if not pending.any():
            break
        r, j_out, j_m, gap = _trim(shoot(
            shot_build, shot_th, _pad(y, kp), _pad(pending, kp) & (np.arange(kp) < k)[:, None],
            control=s.control, lanes=lanes, driven=driven, **columns), k)
        step = newton_step(j_out[..., :d].reshape(-1, d, d), gap.reshape(-1, d),
                           pending.reshape(-1)).reshape(k, n_cells, d)
        flat = np.asarray(flatten_dynamical(y))
        size = np.asarray(step_residual(
            jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), y),
            step.reshape(-1, d))).reshape(k, n_cells)
        ok = np.asarray(r.status) == 0
        converged = pending & ok & (size < s.tol)
        # an unstable orbit is not a steady state the actuator reaches: status 4
        unstable = converged.copy()
        unstable[converged] = radius_above(np.asarray(j_out)[..., :d][converged],
                                           STABLE_MULTIPLIER)
        status = np.where(unstable, 4, status)
        pending = pending & ~unstable
        converged = converged & ~unstable
        failed = pending & ~ok  # from a Newton iterate: not converged (status 4)
        status = np.where(failed, np.where(stepped, 4, r.status),
                          np.where(converged, 0, status))
        residual = np.where(pending, size, residual)
        if converged.any():
            m = _metric_stack(r)
            values[converged] = np.asarray(m)[converged]
            final = jax.tree_util.tree_map(
                lambda a, b: np.where(converged.reshape(converged.shape + (1,) * (a.ndim - 2)),
                                      a, b), y, final)
            if free:
                a = j_out[converged][..., :d]
                dy = solve_cells(np.eye(d) - a, j_out[converged][..., cols])
                got = np.full(jacs[converged].shape, np.nan)
                got[..., list(free)] = j_m[converged][..., cols] + j_m[converged][..., :d] @ dy
                jacs[converged] = got
        pending = pending & ok & ~converged & np.isfinite(step).all(axis=-1)
        stepped |= pending
        flat = flat + np.where(pending[..., None], step, 0.0)
        y = _host(with_dynamical(y, jnp.asarray(flat)))
    return SteadyResult(values=values, jac=jacs, status=status,
                        state=final, residual=residual)


def _with_rest(rest, initial):
    """``initial`` with every cell whose start state is not finite set to ``rest`` (all of
    them where ``initial`` is None)."""
    if initial is None:
        return rest
    leaves = jax.tree_util.tree_leaves(initial)
    bad = ~np.all([np.isfinite(a).reshape(a.shape[:2] + (-1,)).all(-1) for a in leaves], 0)
    if not bad.any():
        return initial
    return jax.tree_util.tree_map(
        lambda a, r: np.where(bad.reshape(bad.shape + (1,) * (a.ndim - 2)),
                              r, a), initial, rest)


def _trim(tree, k: int):
    """``tree``'s leading (design) axis cut back to ``k`` (undo :func:`_pad`)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:k], tree)


def steady_metrics(build: Callable, theta, settings: Steady = Steady()) -> dict[str, jax.Array]:
    """Metrics of the periodic orbit of one design, differentiable in ``theta``.

    **Arguments:**

    - `build`: ``theta (n,) -> (actuator, loadings)`` (see :func:`solve_designs`).
    - `theta`: ``(n,)`` parameters.
    - `settings`: :class:`Steady`.

    **Returns:**

    ``{name: (C,)}`` for :data:`METRICS` (NaN at failed cells) and ``"status"`` (float,
    0 = ok; zero derivative).
    """
    return implicit(_CellSolver(build, settings), theta)


class _CellSolver(eqx.Module):
    build: Callable
    settings: Steady = eqx.field(static=True)

    def __call__(self, theta: np.ndarray, need_jac: bool):
        r = solve_designs(self.build, theta[None], settings=self.settings, jac=need_jac)
        values = {k: r.values[0, :, i] for i, k in enumerate(METRICS)}
        values["status"] = r.status[0].astype(float)
        jacs = None if r.jac is None else {k: r.jac[0, :, i] for i, k in enumerate(METRICS)}
        return values, jacs
