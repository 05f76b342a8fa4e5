"""Periodic steady states: settle-or-shoot, checked against the papers' long runs.

Paper 000 runs N = 100 cycles from rest and averages the last k. That spends most of its time
where nothing changes any more (a 1 Hz cell settles in a few cycles) and is still short of
steady where the payload is lightly damped (at 129 Hz with M = 2 g, c = 0.1 N s/m the state
still changes by ~1e-4 per cycle after 100 cycles). :func:`periodic_cells` instead

1. runs every cell from rest until its one-period map has converged (the residual, scaled up
   by the observed contraction per cycle, below ``tol``) or for at most ``warmup`` cycles, in
   one engine call (:func:`jaxdea.protocol.run_protocol` with ``settle``), and then
2. finishes the cells that have not settled by Newton shooting on the one-period map
   ``y -> Phi_T(y)``: ``y <- y - (J - I)^-1 (Phi_T(y) - y)`` with ``J = dPhi_T/dy`` from JAX
   forward-mode autodiff through the same engine (one period, all unsettled cells at once;
   the Jacobian of every cell comes from one ``jacfwd`` over the d dynamical states, because
   cells are independent: perturbing every cell's start by the same vector gives each cell's
   own diagonal block).

The metrics of a cell are those of the last cycle integrated from its converged state, and
``residual`` is its periodicity residual there. Cells that do not converge (subharmonic or
chaotic response, or a Newton iteration that does not contract) get status 4, and so do
cells whose converged orbit is unstable (a Floquet multiplier above
:data:`STABLE_MULTIPLIER`: the actuator never settles on it), with a NaN residual (so that
they are never counted steady).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.cone import ConeActuator, ConeState, Loading
from .lane_state import rest_states, select_cells
from .lanes import batch_pools, run_protocol
from .metrics import DYNAMICAL, CycleMetrics, periodicity_residual
from .sharding import cell_sharded, on_accelerator, to_host
from .step_control import StepControl

#: The per-cell metrics of :class:`CycleMetrics` (everything but the final state).
PER_CELL = tuple(f.name for f in dataclasses.fields(CycleMetrics) if f.name != "final_state")


def flatten_dynamical(y: ConeState) -> jax.Array:
    """The dynamical states of ``y`` as one vector per cell: ``(..., d)`` (a numpy array
    where ``y``'s are: the host-side Newton and chord bookkeeping dispatches nothing)."""
    lead = y.q.shape[:-1]
    leaves = [getattr(y, k).reshape(lead + (-1,)) for k in DYNAMICAL]
    xp = np if all(isinstance(a, np.ndarray) for a in leaves) else jnp
    return xp.concatenate(leaves, axis=-1)


def with_dynamical(y: ConeState, flat: jax.Array) -> ConeState:
    """``y`` with its dynamical states replaced by the vectors ``flat`` (inverse of
    :func:`flatten_dynamical`; numpy ``flat`` gives numpy leaves)."""
    out, at = [], 0
    for k in DYNAMICAL:
        leaf = getattr(y, k)
        size = leaf.shape[-1]
        out.append(flat[..., at:at + size].reshape(leaf.shape))
        at += size
    return eqx.tree_at(lambda s: tuple(getattr(s, k) for k in DYNAMICAL), y, tuple(out))


def _settle(budget, loadings, initial, active, *, control, pools, driven):
    """Settle the ``active`` cells from ``initial`` for at most ``cycles`` periods, stopping
    each where its residual is below ``tol``: ``budget = (actuator, cycles, tol)``, the two
    numbers as arrays (traced), so that one compiled program serves every budget. With
    ``(actuator, 1, 0)`` it is one plain period from ``initial`` (a chord iteration, with
    status 4 where the period went well: nothing settles below 0; :func:`one_period`)."""
    actuator, cycles, tol = budget
    return run_protocol(actuator, loadings, cycles=cycles, average=jnp.ones_like(cycles),
                        settle=tol, control=control, pools=pools, driven=driven,
                        initial=initial, active=active)


def settle_program(devices: tuple):
    """The compiled settling program of :func:`_settle` on ``devices``: one per device set,
    shared by the from-rest settling of :func:`periodic_cells` and the one-period calls of
    the chord iterations (:func:`one_period`), so that a warm-started map compiles it once."""
    return cell_sharded(_settle, devices) if len(devices) > 1 else _SETTLE


def settle_pools(n_local: int, lanes: int | None) -> tuple[int, ...]:
    """The lane pools of the settling program for ``n_local`` cells per device and ``lanes``
    lanes per device (default 32): :func:`~jaxdea.engine.lanes.lane_pools` with an early
    exit. A chord iteration's period runs through the same pools, so that one program serves
    both (measured: ``bench/NOTES.md``)."""
    return batch_pools(n_local, lanes)


def settle_budget(actuator, cycles: int, tol: float):
    """``budget`` of :func:`_settle`: the numbers as arrays (traced, not compile-time)."""
    return actuator, np.asarray(cycles, np.int32), np.asarray(tol, np.float64)


def one_period(program, actuator, loadings, initial, active, *, control, pools, driven):
    """One plain period of the ``active`` cells from ``initial`` with the settling
    ``program``: the chord iterations' period (:mod:`jaxdea.engine.chord`).

    **Arguments:**

    - `program`: :func:`settle_program` of the devices the cells are split over.
    - `actuator`, `loadings`: the model and the cells (leading axis).
    - `initial`: host start states, one per cell.
    - `active`: bool per cell; the others are skipped at no cost.
    - `control`, `pools`, `driven`: as for the from-rest settling (:func:`settle_pools`), so
      that the call reuses its compiled program.

    **Returns:**

    Host :class:`CycleMetrics` of that period, status 0 where it went well (the program's
    status 4, "not settled", is what a one-period budget always ends in).
    """
    r = to_host(program(settle_budget(actuator, 1, 0.0), loadings, initial, active,
                        control=control, pools=pools, driven=driven))
    return eqx.tree_at(lambda m: m.status, r, np.where(r.status == 4, 0, r.status))


def shoot_period(actuator, loadings, y, active, *, control, lanes, driven):
    """One period from ``y`` for the ``active`` cells: its metrics, the Jacobian ``J`` of the
    one-period map and the gap ``Phi_T(y) - y`` of each cell (the Newton step is solved on the
    host, :func:`newton_step`)."""
    flat = flatten_dynamical(y)
    d = flat.shape[-1]

    def period_map(delta):
        # one pool: every shooting cell runs one period, there is no tail to compact
        res = run_protocol(actuator, loadings, cycles=1, average=1,
                           initial=with_dynamical(y, flat + delta), active=active,
                           control=control, pools=(lanes,), driven=driven,
                           frozen_steps=True)
        out = flatten_dynamical(res.final_state)
        return out, (out, res)

    jac, (out, res) = jax.jacfwd(period_map, has_aux=True)(jnp.zeros(d, flat.dtype))
    return res, jac, out - flat


def newton_step(jac: np.ndarray, gap: np.ndarray, active: np.ndarray) -> np.ndarray:
    """The Newton step ``-(J - I)^-1 (Phi_T(y) - y)`` of every active cell (0 elsewhere).

    Solved on the host with numpy, never inside the sharded device program: a batched
    ``jnp.linalg.solve`` there is a LAPACK call that splits its batch over XLA's intra-op
    thread pool from a pool thread, and with one device per core every pool thread ends up
    waiting for the others (a deadlock seen on a 480-cell periodic map over 2 devices).

    **Arguments:**

    - `jac`: ``(n, d, d)`` Jacobians of the one-period map.
    - `gap`: ``(n, d)`` gaps ``Phi_T(y) - y``.
    - `active`: ``(n,)`` bool, the cells that take a step.

    **Returns:**

    ``(n, d)`` steps; NaN for an active cell whose ``J - I`` is singular or not finite (a
    period map with a multiplier at 1: the orbit is not isolated, and Newton cannot go on).
    """
    jac, gap = np.asarray(jac), np.asarray(gap)
    step = np.zeros(gap.shape, np.result_type(jac, gap))
    idx = np.flatnonzero(np.asarray(active))  # late in a chain: a few cells of many
    if idx.size:
        eye = np.eye(step.shape[-1], dtype=step.dtype)
        step[idx] = -solve_cells(jac[idx] - eye, gap[idx, :, None])[..., 0]
    return step


def solve_cells(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 b`` per cell (leading axis), NaN for a cell whose ``a`` is singular or whose
    ``a`` or ``b`` is not finite (numpy's batched solve would raise for the whole batch).

    **Arguments:**

    - `a`: ``(n, d, d)``; `b`: ``(n, d, k)``.

    **Returns:**

    ``(n, d, k)``.
    """
    fine = np.isfinite(a).all(axis=(1, 2)) & np.isfinite(b).all(axis=(1, 2))
    eye = np.eye(a.shape[-1], dtype=a.dtype)
    a = np.where(fine[:, None, None], a, eye)
    b = np.where(fine[:, None, None], b, 0.0)
    try:
        x = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:  # a singular cell: solve one by one
        x = np.empty(b.shape, dtype=np.result_type(a, b))
        for i in range(a.shape[0]):
            try:
                x[i] = np.linalg.solve(a[i], b[i])
            except np.linalg.LinAlgError:
                fine[i] = False
    return np.where(fine[:, None, None], x, np.nan)


#: Largest Floquet multiplier (spectral radius of the one-period map's Jacobian) of an
#: orbit counted as stable. Newton shooting converges to unstable periodic orbits too; the
#: actuator never settles on one (its trajectory from rest stays aperiodic: on a 40 kV
#: DCDEA-LS map, 6 cells whose 100-cycle runs kept residuals of 0.4-1.3 had Newton orbits
#: with P_out up to 1.7x off), so such a cell gets status 4. The margin above 1 covers the
#: error of a multiplier near 1 (a lightly damped, marginally stable orbit).
STABLE_MULTIPLIER = 1.0 + 1e-3


def floquet_radius(jac: np.ndarray) -> np.ndarray:
    """Spectral radius of each one-period map's Jacobian ``(n, d, d) -> (n,)`` (NaN where
    the Jacobian is not finite): the orbit is stable if it is below 1."""
    fine = np.isfinite(jac).all(axis=(1, 2))
    safe = np.where(fine[:, None, None], jac, 0.0)
    return np.where(fine, np.abs(np.linalg.eigvals(safe)).max(axis=-1), np.nan)


#: Squarings of :func:`radius_above`'s bound (``k = 2^8``).
RADIUS_SQUARINGS = 8


def radius_above(jac: np.ndarray, bound: float) -> np.ndarray:
    """Whether each one-period map's Floquet radius is above ``bound`` (true where its
    Jacobian is not finite): ``~(floquet_radius(jac) <= bound)``, with the eigenvalues
    computed only where the bound ``rho(J) <= ||J^k||^(1/k)`` (infinity norm, ``k`` =
    :data:`RADIUS_SQUARINGS` squarings, rescaled after each) does not show the radius below
    ``bound`` already: batched 5 x 5 products are several times cheaper than numpy's
    ``eigvals``, and a Jacobian in SI units is far from normal, so ``k`` must be large.

    **Arguments:**

    - `jac`: ``(n, d, d)`` Jacobians of the one-period map.
    - `bound`: the radius to compare with.

    **Returns:**

    ``(n,)`` bool.
    """
    jac = np.asarray(jac)
    fine = np.isfinite(jac).all(axis=(1, 2))
    power = np.where(fine[:, None, None], jac, 0.0)
    log_scale = np.zeros(jac.shape[0])  # J^(2^i) = exp(log_scale) * power
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        for _ in range(RADIUS_SQUARINGS):
            norm = np.abs(power).sum(axis=2).max(axis=1)
            norm = np.where(norm > 0, norm, 1.0)  # a zero matrix stays zero
            power = power / norm[:, None, None]
            log_scale = 2.0 * (log_scale + np.log(norm))
            power = power @ power
        norm = np.abs(power).sum(axis=2).max(axis=1)
        log_bound = (log_scale + np.log(norm)) / 2.0 ** RADIUS_SQUARINGS
    below = fine & (log_bound <= np.log(float(bound)))
    above = ~below
    check = np.flatnonzero(fine & ~below)
    above[check] = ~(floquet_radius(jac[check]) <= bound)
    return above


#: Lane pool of the shooting stage. Its lanes carry the d forward-mode tangents of
#: ``jacfwd`` too (~9x the primal work), so the primal engine's best width (128) is far too
#: wide here: on 2 cores, the periodic bench sweep (128 cells, 115 of them shot) took 0.57 /
#: 0.52 / 0.51 / 0.94 / 1.55 s with 4 / 8 / 16 / 32 / 64 shooting lanes.
SHOOTING_LANES = 16


def shooting_lanes(lanes: int | None, devices: tuple = ()) -> int:
    """The shooting stage's lane pool: :data:`SHOOTING_LANES` (at most ``lanes``) on CPU
    devices; on accelerators ``lanes`` itself, where a narrow pool's step costs as much as a
    wide one's (:func:`~jaxdea.engine.sharding.on_accelerator`)."""
    if lanes and on_accelerator(devices):
        return int(lanes)
    return min(lanes or SHOOTING_LANES, SHOOTING_LANES)


def periodic_cells(actuator: ConeActuator, loadings: Loading, *, tol: float = 1e-6,
                   warmup: int = 12, newton: int = 6, control: StepControl = StepControl(),
                   lanes: int | None = None, devices: tuple | None = None,
                   driven: tuple[int, ...] | None = None,
                   initial: ConeState | None = None, active: np.ndarray | None = None,
                   with_jacobian: bool = False):
    """Periodic steady state of every cell of ``loadings`` (leading axis = cells).

    ``tol``: convergence tolerance on the scaled state (:func:`periodicity_residual`; 1e-6
    keeps P_out within ~1e-4 of the converged value); ``warmup``: most cycles from rest
    before shooting takes over; ``newton``: most Newton iterations. Returns
    :class:`CycleMetrics` over one period of the steady state; ``steps`` and ``cycles_run``
    count the primal work of all stages (the tangents of the shooting stage come on top).
    ``lanes``: lane pool of the settling stage (per device; default 32); shooting uses at
    most :data:`SHOOTING_LANES`. ``devices``: split the cells over these JAX devices (their
    number must divide the cell count); default: one device. ``driven``: the driven
    membranes (:func:`jaxdea.protocol.run_protocol`; default all). ``initial``: start state
    of every cell for the settling stage (leading axis = cells; default: rest). ``active``:
    bool per cell, solve only these (the others are skipped at no cost; their metrics are
    meaningless). ``with_jacobian``: also return the one-period map's Jacobian ``(n, d, d)``
    at each cell's last Newton iterate (NaN for a cell that settled without shooting), for
    :func:`jaxdea.engine.chord.chord_cells`.
    """
    for name, v, lo in (("warmup", warmup, 2), ("newton", newton, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise ValueError(f"tol = {tol!r} is outside the allowed range (0, 1)")
    devices = tuple(devices or jax.devices()[:1])
    settle = settle_program(devices)
    shoot = cell_sharded(shoot_period, devices) if len(devices) > 1 else _SHOOT
    driven = None if driven is None else tuple(int(j) for j in driven)
    # Every stage's results come to the host (to_host) before the Newton bookkeeping below
    # mixes them with the host masks: on the devices, a sharded array combined with a
    # replicated one may compile to a collective, which XLA aborts on when one device is
    # 40 s late. Cells are independent; nothing here needs one.
    active = None if active is None else np.asarray(active, bool)
    n = jax.tree_util.tree_leaves(loadings)[0].shape[0]
    if initial is None:  # rest, given explicitly: the one-period calls' program (initial set)
        initial = to_host(_REST(actuator, loadings))
    res = to_host(settle(settle_budget(actuator, warmup, tol), loadings, initial,
                         np.ones(n, bool) if active is None else active, control=control,
                         pools=settle_pools(n // len(devices), lanes), driven=driven))
    out = {k: np.asarray(getattr(res, k)) for k in PER_CELL}
    final = res.final_state
    y = res.final_state
    pending = out["status"] == 4
    if active is not None:
        pending &= active
    jacobian = None
    if with_jacobian:
        d = flatten_dynamical(y).shape[-1]
        jacobian = np.full(pending.shape + (d, d), np.nan)
    stepped = np.zeros_like(pending)
    for _ in range(int(newton)):
        if not pending.any():
            break
        r, jac, gap = to_host(shoot(actuator, loadings, y, pending, control=control,
                                    lanes=shooting_lanes(lanes, devices),
                                    driven=driven))
        if with_jacobian:
            jacobian = np.where(pending[:, None, None], np.asarray(jac), jacobian)
        step = newton_step(np.asarray(jac), np.asarray(gap), pending)
        size = np.asarray(step_residual(y, step))
        rs = {k: np.asarray(getattr(r, k)) for k in out}
        for k in out:
            if k in ("steps", "cycles_run"):
                out[k] = out[k] + np.where(pending, rs[k], 0)
            elif k != "status":
                out[k] = np.where(pending, rs[k], out[k])
        ok = rs["status"] == 0
        converged = pending & ok & (size < tol)  # NaN size (no Newton step) never converges
        unstable = converged.copy()
        unstable[converged] = radius_above(np.asarray(jac)[converged], STABLE_MULTIPLIER)
        # a period that fails from the settled state is the actuator's own failure (its
        # status); one that fails from a Newton iterate (an extrapolated state, not on the
        # trajectory) only says that Newton did not converge: status 4
        failed = pending & ~ok
        out["status"] = np.where(failed, np.where(stepped, 4, rs["status"]),
                                 np.where(converged & ~unstable, 0, out["status"]))
        out["residual"] = np.where(unstable, np.nan, out["residual"])
        final = to_host(select_cells(pending, r.final_state, final))
        pending = pending & ok & ~converged & np.isfinite(step).all(axis=1)
        stepped |= pending
        y = to_host(with_dynamical(y, flatten_dynamical(y) + np.where(pending[:, None], step,
                                                                      0.0)))
    metrics = CycleMetrics(final_state=jax.tree_util.tree_map(jnp.asarray, final),
                           **{k: jnp.asarray(v) for k, v in out.items()})
    return (metrics, jacobian) if with_jacobian else metrics


@eqx.filter_jit
def step_residual(y: ConeState, step: jax.Array) -> jax.Array:
    """Periodicity residual between ``y`` and ``y + step`` per cell (one device): the size
    of a Newton step, in the scaled norm of :func:`periodicity_residual`."""
    return jax.vmap(periodicity_residual)(
        with_dynamical(y, flatten_dynamical(y) + step), y)


_SETTLE = eqx.filter_jit(_settle)
_REST = eqx.filter_jit(rest_states)
_SHOOT = eqx.filter_jit(shoot_period)
