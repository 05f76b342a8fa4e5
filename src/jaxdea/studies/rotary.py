"""Studies of the rotational double cone (paper 003): time integration to rest (diffrax), the
batched (r_i, d) steady-angle study of Fig 12, and gradient design optimisation of the angle.

The model and its static equilibrium are :mod:`jaxdea.models.rotary`.
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr
from jaxtyping import Array, ArrayLike

from .._checks import SweepError, finite_array
from ..models.rotary import (
    ELEMENTS,
    INVALID,
    ROTARY_STATUS,
    RotaryDCDEA,
    equilibrium,
    f64,
    scales,
    steady_angle,
)

# ---- time integration (diffrax) -----------------------------------------------------------


def _rest_event(tol: float, t_min):
    """Event: at rest when ``t > t_min`` and every scaled velocity ``|G'/L|, |theta'|`` is
    below ``tol`` (1/s). (diffrax's ``steady_state_event`` fires at t = 0, where the
    unactuated spacer is at rest before the drive rises.)"""

    def cond_fn(t, y, args, **kwargs):
        model = args[1]
        vel = jnp.abs(y[3:] / scales(model))
        return (t > t_min) & (jnp.max(vel) < tol)

    return diffrax.Event(cond_fn)


@eqx.filter_jit
def _integrate(model: RotaryDCDEA, drive, y0, t_end, ts, rtol, atol, rest_tol, t_min,
               max_steps: int = 200_000):
    """diffrax Tsit5 with a PID controller (the system is overdamped but only mildly stiff:
    an explicit solver compiles in seconds where an implicit one takes tens; all numbers are
    passed as arrays so new values do not recompile). Saves at ``ts``
    and at the end; stops early at rest (:func:`_rest_event`; ``rest_tol = 0`` never fires).
    One compiled function serves :func:`simulate_rotary` and :func:`settle`."""
    term = diffrax.ODETerm(lambda t, y, args: args[1].vector_field(t, y, args[0]))
    sol = diffrax.diffeqsolve(
        term, diffrax.Tsit5(), t0=0.0, t1=t_end, dt0=1e-5, y0=y0, args=(drive, model),
        saveat=diffrax.SaveAt(ts=ts, t1=True),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps, event=_rest_event(rest_tol, t_min), throw=False,
    )
    return sol.ts, sol.ys, sol.result, sol.stats["num_steps"]


def simulate_rotary(model: RotaryDCDEA, t_end: float = 1.0, n_save: int = 401, drive=None,
                    rtol: float = 1e-8, atol: float = 1e-12):
    """Dynamic response (paper 003 eqs 3-5 with eq 10's viscous term) to ``drive`` (default:
    the filtered step to the eq-30 voltage, :class:`FilteredStep`) from the unactuated
    equilibrium.

    Returns an ``xarray.Dataset`` over ``t`` (s): ``theta_deg``, ``G_x``, ``G_y`` (m) and per
    element ``stretch``, ``force`` (N), ``voltage`` (V), ``field`` (V/m).
    """
    import xarray as xr

    drive = model.drive() if drive is None else drive
    ts = jnp.linspace(0.0, t_end, n_save)  # n_save = 401 shares settle's compilation
    ts_out, ys, result, _ = _integrate(model, drive, model.initial_state(), *map(
        f64, (t_end, ts, rtol, atol, 0.0, 0.0)))
    if not bool(result == diffrax.RESULTS.successful):
        raise RuntimeError(f"diffrax failed: {result}")
    ts_out, ys = ts_out[:-1], ys[:-1]  # drop the t1 copy
    obs = _observe(model, drive, ts_out, ys)
    el = ("t", "element")
    return xr.Dataset(
        {
            "theta_deg": (("t",), np.degrees(np.asarray(obs["theta"])), {"units": "deg"}),
            "G_x": (("t",), np.asarray(obs["G_x"]), {"units": "m"}),
            "G_y": (("t",), np.asarray(obs["G_y"]), {"units": "m"}),
            "stretch": (el, np.asarray(obs["stretch"]), {"units": "1"}),
            "force": (el, np.asarray(obs["force"]), {"units": "N"}),
            "voltage": (el, np.asarray(obs["voltage"]), {"units": "V"}),
            "field": (el, np.asarray(obs["field"]), {"units": "V/m"}),
        },
        coords={"t": ("t", np.asarray(ts_out), {"units": "s"}), "element": list(ELEMENTS)},
        attrs={"r_i": float(model.r_i), "d": float(model.d), "field_mode": model.field},
    )


@eqx.filter_jit
def _observe(model: RotaryDCDEA, drive, ts, ys) -> dict:
    return jax.vmap(lambda t, y: model.observables(t, y, drive))(ts, ys)


class Settled(NamedTuple):
    """Result of :func:`settle`: final ``q`` (3,), time at rest ``t`` (s), solver steps."""

    q: Array
    t: Array
    steps: Array


def settle(model: RotaryDCDEA, drive=None, t_end: float = 30.0, rtol: float = 1e-10,
           atol: float = 1e-14, rest_tol: float = 1e-9, n_save: int = 401) -> Settled:
    """Integrate the dynamics (diffrax) from the unactuated equilibrium until rest: after
    ``3 filter_time``, every scaled velocity below ``rest_tol`` 1/s (with the ~0.2 s slowest
    time constant of Table 1 that leaves ~1e-10 rad of motion to go)."""
    drive = model.drive() if drive is None else drive
    t_min = 3.0 * getattr(drive, "tau", 0.0)
    grid = jnp.linspace(0.0, t_end, n_save)  # same shape as simulate_rotary: one compilation
    ts, ys, result, steps = _integrate(model, drive, model.initial_state(), *map(
        f64, (t_end, grid, rtol, atol, rest_tol, t_min)))
    if not bool(result == diffrax.RESULTS.event_occurred):
        raise RuntimeError(f"diffrax did not reach rest by t = {t_end} s: {result}")
    last = int(jnp.sum(jnp.isfinite(ts))) - 1  # saves after the event are inf; t1 = event
    return Settled(q=ys[last, :3], t=ts[last], steps=steps)


# ---- batched (r_i, d) study (paper 003 Fig 12) ----------------------------------------------


@eqx.filter_jit
def _study_kernel(model: RotaryDCDEA, ri: Array, d: Array):
    def cell(r, dd):
        m = model.with_geometry(r, dd)
        sol = equilibrium(m)
        return sol.q[2], sol.status, m.voltage_max(), m.rest_stretch(), sol.min_eig

    return jax.vmap(cell)(ri, d)


def _study_cells(model: RotaryDCDEA, ri: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`_study_kernel` on flat cells, its results as numpy arrays (a Dask task)."""
    return tuple(np.asarray(a) for a in _study_kernel(model, jnp.asarray(ri), jnp.asarray(d)))


def _on_cluster(client, model, ri: np.ndarray, d: np.ndarray, chunk: int | None):
    """The flat cells in equal chunks (the last padded by repeating its last cell), one Dask
    task each, the results put back in cell order."""
    from .distributed import CHUNKS_PER_WORKER, check_client, padded_cells

    n_workers = check_client(client)
    n = ri.size
    chunk = int(chunk or max(1, -(-n // (CHUNKS_PER_WORKER * n_workers))))
    futures = []
    for lo in range(0, n, chunk):
        idx = padded_cells(lo, chunk, n)
        futures.append(client.submit(_study_cells, model, ri[idx], d[idx], pure=False))
    parts = client.gather(futures)
    return tuple(np.concatenate([p[k] for p in parts])[:n] for k in range(len(parts[0])))


def rotary_study(model: RotaryDCDEA, ri: ArrayLike, d: ArrayLike, *, client=None,
                 chunk: int | None = None) -> xr.Dataset:
    """Steady angle of the rotary double cone over the grid ``ri x d`` in ONE vmapped, jitted
    call (paper 003 Fig 12), or one such call per chunk of cells on a Dask cluster. Each cell
    uses its own eq-30 voltage on the model's activation pattern.

    **Arguments:**

    - `model`: a :class:`~jaxdea.RotaryDCDEA` (e.g. from ``configs/rotary_dcdea.toml``).
    - `ri`: inner radii r_i, m (1-D).
    - `d`: half spacer lengths d, m (1-D).
    - `client`: a ``dask.distributed.Client``: the cells run as tasks on its workers, in
      equal chunks (the same numbers as one call, to the last bits of XLA's vectorisation).
    - `chunk`: cells per task (default: about
      :data:`~jaxdea.studies.distributed.CHUNKS_PER_WORKER` tasks per worker).

    **Returns:**

    An ``xarray.Dataset`` with dims ``(ri, d)``: ``theta_deg`` (NaN unless ``status == 0``),
    ``status`` (codes in ``attrs['status_codes']``), ``voltage`` (V), ``rest_stretch``,
    ``min_stiffness_eig`` (N m).
    """
    # lengths: finite and > 0 (a grid may still reach past the geometry's limits, r_i >= r_o
    # for instance: those points get status 3, the others are solved)
    ri = finite_array("ri", ri, positive=True)
    d = finite_array("d", d, positive=True)
    if ri.ndim != 1 or d.ndim != 1:
        raise SweepError("ri and d must be 1-D arrays of metres")
    if chunk is not None and (isinstance(chunk, bool) or int(chunk) != chunk or chunk < 1):
        raise SweepError(f"chunk must be an integer >= 1 (cells per task), got {chunk!r}")
    RI, D = np.meshgrid(ri, d, indexing="ij")
    if client is None:
        theta, status, volt, lam0, eig = _study_kernel(model, jnp.asarray(RI.ravel()),
                                                       jnp.asarray(D.ravel()))
    else:
        theta, status, volt, lam0, eig = _on_cluster(client, model, RI.ravel(), D.ravel(),
                                                      chunk)
    shape = RI.shape
    dims = ("ri", "d")
    status = np.asarray(status).reshape(shape)
    theta = np.where(status == 0, np.degrees(np.asarray(theta)).reshape(shape), np.nan)
    valid = status != INVALID
    return xr.Dataset(
        {
            "theta_deg": (dims, theta, {"units": "deg", "long_name": "steady rotation angle"}),
            "status": (dims, status.astype(np.int32)),
            "voltage": (dims, np.where(valid, np.asarray(volt).reshape(shape), np.nan),
                        {"units": "V", "long_name": "eq-30 voltage"}),
            "rest_stretch": (dims, np.where(valid, np.asarray(lam0).reshape(shape), np.nan),
                             {"units": "1"}),
            "min_stiffness_eig": (dims, np.asarray(eig).reshape(shape), {"units": "N m"}),
        },
        coords={"ri": ("ri", ri, {"units": "m"}), "d": ("d", d, {"units": "m"})},
        attrs={"model": "rotary_dcdea", "field_mode": model.field,
               "pattern": np.asarray(model.pattern).tolist(),
               "gravity": float(model.gravity),
               "status_codes": "; ".join(f"{k}: {v}" for k, v in ROTARY_STATUS.items())},
    )


# ---- design optimisation ------------------------------------------------------------------


def optimise_design(model: RotaryDCDEA, start=(4e-3, 12e-3),
                    bounds=((2e-3, 7e-3), (4e-3, 18e-3)), *, maxiter: int = 100,
                    gtol: float = 1e-9) -> dict:
    """Maximise the steady angle ``|theta|`` over ``(r_i, d)`` within ``bounds`` (m) by
    L-BFGS-B with exact gradients (IFT through the equilibrium, :func:`steady_angle`).

    Returns ``dict(r_i, d, theta_deg, nit, success, path)`` (``path``: the iterates, m).
    """
    from scipy.optimize import minimize

    lo = np.array([b[0] for b in bounds]) * 1e3
    hi = np.array([b[1] for b in bounds]) * 1e3
    fun = angle_objective
    path = []

    def f(x_mm):
        x = np.clip(x_mm, lo, hi)
        val, grad = fun(model, jnp.asarray(x * 1e-3))
        path.append(x * 1e-3)
        return float(val), np.asarray(grad, dtype=np.float64) * 1e-3

    res = minimize(f, np.asarray(start, dtype=np.float64) * 1e3, jac=True, method="L-BFGS-B",
                   bounds=list(zip(lo, hi)), options={"maxiter": maxiter, "gtol": gtol,
                                                      "ftol": 1e-15})
    x = np.clip(res.x, lo, hi) * 1e-3
    theta = -float(fun(model, jnp.asarray(x))[0])
    return {"r_i": float(x[0]), "d": float(x[1]), "theta_deg": theta, "nit": int(res.nit),
            "success": bool(res.success), "path": np.array(path)}


def _neg_angle(x: Array, model: RotaryDCDEA) -> Array:
    """-|theta| in degrees at geometry ``x = [r_i, d]`` (m)."""
    return -jnp.abs(jnp.degrees(steady_angle(model.with_geometry(x[0], x[1]))))


@eqx.filter_jit
def angle_objective(model: RotaryDCDEA, x: Array) -> tuple[Array, Array]:
    """``(model, [r_i, d]) -> (-|theta| in deg, gradient)``, jitted once per model structure."""
    return jax.value_and_grad(_neg_angle)(x, model)
