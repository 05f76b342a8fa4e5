"""Trajectories of one drive case, through ``diffrax.diffeqsolve``.

For plots and inspection (time histories like paper 000 Fig 8). Cycle-averaged metrics over
many cells use :mod:`jaxdea.protocol`, which steps the same solver without storing anything.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr

from .._checks import SweepError, check_protocol
from ..models.cone import Model
from ..solver import LawsonRK4, SemilinearTerm
from .loadings import check_payload, make_loadings, payload_parameters, warn_breakdown


@eqx.filter_jit
def _solve(actuator, loading, ts):
    term = SemilinearTerm(actuator.vector_field, actuator.linearisation)
    sol = diffrax.diffeqsolve(
        term, LawsonRK4(), t0=ts[0], t1=ts[-1], dt0=None,
        y0=actuator.initial_state(loading.payload), args=loading, saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.StepTo(ts=ts), max_steps=ts.shape[0],
    )
    obs = jax.vmap(lambda t, y: actuator.observables(t, y, loading))(sol.ts, sol.ys)
    return sol.ys, obs


def time_grid(frequency: float, cycles: int, points_per_cycle: int,
              edge_fractions: np.ndarray) -> np.ndarray:
    """Uniform grid of ``points_per_cycle`` per period plus every drive edge, sorted."""
    k = np.arange(cycles * points_per_cycle + 1) / points_per_cycle
    edges = (np.arange(cycles)[:, None] + np.asarray(edge_fractions)[None, :]).ravel()
    return np.unique(np.round(np.concatenate([k, edges]), 12)) / frequency


def simulate(model: Model, *, mass: float | None = None, damping: float | None = None,
             freq: float, payload=None, drive: str = "A", phase: float = 0.0,
             cycles: int = 10, points_per_cycle: int = 400) -> xr.Dataset:
    """Time history of one cone drive case from rest (fixed Lawson RK4 steps, edges on the
    grid), for plots and checks; power studies use :func:`jaxdea.sweep`.

    **Arguments:**

    - `model`: a square-wave cone from :func:`jaxdea.load_config`.
    - `mass`, `damping`: the payload, kg and N s/m.
    - `payload`: a payload law (:class:`jaxdea.Drag`, ...) instead of `damping` (`mass` may
      then be omitted), as in :func:`jaxdea.sweep`.
    - `freq`: drive frequency, Hz.
    - `drive`: ``"A"``, ``"B"`` or ``"both"``; `phase`: B's delay with ``"both"``, rad.
    - `cycles`: drive periods to integrate; `points_per_cycle`: samples (= steps) per period
      (>= 8; every drive edge is added to the grid).

    **Returns:**

    An ``xarray.Dataset`` over ``t`` (s) with the payload position and velocity and each
    membrane's deflection, force, DEA voltage, source voltage, current and charge (SI units
    in the attrs).
    """
    check_protocol(cycles, 1)
    if points_per_cycle < 8:
        raise SweepError(f"points_per_cycle must be >= 8, got {points_per_cycle}")
    mass_arr, _, payload = check_payload(mass, damping, payload)
    loading = jax.tree_util.tree_map(lambda a: a[0], make_loadings(
        model, mass_arr[0], damping, freq, drive, phase, payload))
    warn_breakdown(model)
    ts = time_grid(float(freq), cycles, points_per_cycle,
                   np.asarray(loading.drive.edge_fractions()))
    ys, obs = _solve(model.actuator, loading, jnp.asarray(ts))
    names = list(model.actuator.membrane_names)
    per_mem = {"deflection": "m", "membrane_force": "N", "dea_voltage": "V",
               "source_voltage": "V", "current": "A"}
    data = {
        "payload_position": (("t",), np.asarray(obs["payload_position"]), {"units": "m"}),
        "payload_velocity": (("t",), np.asarray(obs["payload_velocity"]), {"units": "m/s"}),
        "charge": (("t", "membrane"), np.asarray(ys.charge), {"units": "C"}),
    }
    for k, unit in per_mem.items():
        data[k] = (("t", "membrane"), np.asarray(obs[k]), {"units": unit})
    return xr.Dataset(
        {k: xr.Variable(*v) for k, v in data.items()},
        coords={"t": xr.Variable(("t",), ts, {"units": "s"}), "membrane": names},
        attrs=dict(model=model.name, drive=drive, phase=float(phase), mass=float(mass_arr[0]),
                   **({"damping": float(damping)} if payload is None
                      else payload_parameters(payload)), freq=float(freq)),
    )
