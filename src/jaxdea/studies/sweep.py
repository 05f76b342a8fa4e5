"""Frequency sweeps of a configured model: the papers' protocol over an f axis, as xarray.

The whole frequency axis is one jitted computation (:func:`jaxdea.engine.lanes.run_protocol`);
there is no Python loop over frequencies.
"""

from __future__ import annotations

import jax
import numpy as np
import xarray as xr

from .._checks import SweepError, check_choice, check_early_exit, check_unit_interval, finite_array
from ..engine.batch import DIRECTIONS, EARLY_EXIT, PROTOCOLS, chain_successors, run_cells
from ..engine.metrics import STATUS, STEADY_RESIDUAL, CycleMetrics, steady_cells
from ..engine.precision import check_precision
from ..engine.protocols import Protocol, as_keywords, check_rest_start
from ..engine.step_control import (
    StepControl,
    check_control,
    control_attrs,
    resolve_extrapolate,
)
from ..models.cone import Model
from ..payloads import PARAMETER_UNITS
from .loadings import (
    check_cone_model,
    check_model_ranges,
    check_payload,
    make_loadings,
    payload_parameters,
    warn_breakdown,
)

#: Units and descriptions of the per-cell outputs.
VARIABLES = {
    "P_out": ("W", "mean power dissipated in the payload's dissipative elements over the "
                   "averaging window (paper 000 eq 19: c v^2 for the linear dashpot)"),
    "P_in": ("W", "mean electrical input power without energy recovery (eq 20)"),
    "P_in_signed": ("W", "mean of Phi_in * i, charge returned to the source counted"),
    "efficiency": ("1", "P_out / P_in (eq 21)"),
    "amplitude": ("m", "half peak-to-peak payload displacement over the window"),
    "v_rms": ("m/s", "RMS payload velocity over the window"),
    "status": ("1", "; ".join(f"{k} = {v}" for k, v in STATUS.items())),
    "steps": ("1", "solver steps taken (accepted and rejected)"),
    "residual": ("1", "periodicity residual: scaled max-norm of the state change over the "
                      "last cycle (0 = exactly periodic)"),
    "cycles_run": ("1", "drive cycles integrated for the cell (all stages)"),
}
#: The extra per-cell variable of a warm-started map (``start="neighbour"``,
#: :func:`jaxdea.engine.coexist.coexisting`).
COEXIST = {
    "coexist": ("1", "true where another stable periodic orbit was found: solved from the "
                     "neighbouring mass's orbit (same c and f), or continued along f from "
                     "the neighbouring frequencies' orbits, the cell converged to an orbit "
                     "other than the reported one, continued along c (coexisting responses, "
                     "e.g. near a jump); false: none was found"),
}


def map_variables(start: str = "rest") -> dict[str, tuple[str, str]]:
    """The per-cell variables of a map (name -> (unit, meaning)): :data:`VARIABLES`, and
    with warm starts (``start="neighbour"``) :data:`COEXIST`."""
    return {**VARIABLES, **(COEXIST if start == "neighbour" else {})}


#: What P_out is, for the attrs of every study.
P_OUT_MEANING = ("power dissipated in the payload's dissipative elements (drag, friction); "
                 "springs and gravity store and return energy: they are not output power")
#: The steady flag, derived from status and residual (:func:`~jaxdea.engine.metrics.steady_cells`).
STEADY = ("1", f"true where the last cycle ran to its end (status 0 or 4) and repeated itself: "
               f"periodicity residual <= {STEADY_RESIDUAL:g}; false: the averages are not a "
               "steady-state power")


def sweep(model: Model, *, mass: float | None = None, damping: float | None = None, freq,
          payload=None, drive: str = "A",
          phase: float = 0.0, cycles: int = 100, average: int = 5,
          control: StepControl = StepControl(), lanes: int | None = None,
          protocol: str | Protocol = "paper", direction: str = "forward",
          tol: float = 1e-6, early_exit: float | None = EARLY_EXIT) -> xr.Dataset:
    """Frequency response of ``model``.

    ``mass`` (kg) and ``damping`` (N s/m) of the payload, ``freq`` (Hz, 1-D), ``drive`` one of
    ``"A"``, ``"B"``, ``"both"``; ``phase`` (rad) of B relative to A when both are driven.
    ``payload``: a payload law instead of ``damping`` (:class:`jaxdea.Drag`,
    :class:`jaxdea.LinearViscous`; ``mass`` may then be omitted: the law's mass is used);
    ``damping=c`` is the shorthand for ``LinearViscous(mass, c)``. P_out is the power
    dissipated in the payload's dissipative elements; the law and its parameters are in the
    attrs (``payload``, ``payload_<parameter>``).
    ``protocol="paper"`` (default): each frequency runs ``cycles`` periods from rest; metrics
    average the last ``average``. ``"continuation"``: the same, but each frequency starts from
    the previous one's final state, in ``freq`` order (``direction="backward"``: from the
    highest frequency down) — paper 000's forward sweep, and the backward one that exposes
    jumps. ``"periodic"``: the periodic steady state to tolerance ``tol``
    (:mod:`jaxdea.engine.periodic`). ``early_exit``: paper and continuation cells stop once periodic
    to this tolerance (:data:`EARLY_EXIT`; ``None``: every cell runs all ``cycles``). The
    cells are split over all JAX devices (:func:`jaxdea.use_cpu_cores` makes one per CPU
    core). Returns a Dataset with dimension ``f`` and variables P_out, P_in,
    P_in_signed, efficiency, amplitude, v_rms, status, steps, residual, cycles_run and
    steady (false where the last cycles are not periodic; units in attrs).

    ``protocol`` may also be a protocol object, e.g. ``Paper(cycles=10, average=2)``
    (:class:`jaxdea.Paper`, :class:`jaxdea.Continuation`, :class:`jaxdea.Periodic`): its
    settings are then used, and ``cycles``, ``average``, ``early_exit``, ``direction`` and
    ``tol`` must stay at their defaults (:class:`SweepError` naming the one that does not).
    The result equals the string form's with the same settings, attrs included.
    """
    check_rest_start(protocol, "a sweep (one payload)")
    protocol, (cycles, average, early_exit, direction, tol) = as_keywords(
        protocol, cycles=cycles, average=average, early_exit=early_exit, direction=direction,
        tol=tol)
    check_choice("protocol", protocol, PROTOCOLS)
    check_choice("direction", direction, DIRECTIONS)
    check_unit_interval("tol", tol)
    check_early_exit(early_exit)
    check_control(control)
    check_precision(control, protocol, early_exit)
    freq = finite_array("freq", freq, positive=True)
    if freq.ndim != 1:
        raise SweepError(f"freq must be 1-D, got shape {freq.shape}")
    for name, v in (("mass", mass), ("damping", damping)):
        if v is not None and np.ndim(v) != 0:
            raise SweepError(f"{name} must be a scalar for a sweep (use powermap for grids)")
    check_cone_model(model)
    check_model_ranges(model)  # a model edited in code, as a config would be
    mass_arr, _, payload = check_payload(mass, damping, payload)
    loadings = make_loadings(model, mass_arr[0], damping, freq, drive, phase, payload)
    warn_breakdown(model)
    successor = chain_successors(freq.size, direction=direction)
    control = resolve_extrapolate(control, freq.size, early_exit)
    devices = tuple(jax.devices())
    res = run_cells(model, loadings, cycles=cycles, average=average, control=control,
                    lanes=lanes, protocol=protocol, successor=successor, tol=tol,
                    early_exit=early_exit, devices=devices)
    return to_dataset(res, {"f": freq}, attrs=dict(
        model=model.name, drive=drive, phase=float(phase), mass=float(mass_arr[0]),
        **({"damping": float(damping)} if payload is None else payload_parameters(payload)),
        P_out_meaning=P_OUT_MEANING,
        protocol=protocol,
        direction=direction if protocol == "continuation" else None,
        tol=float(tol) if protocol == "periodic" else None,
        early_exit=(float(early_exit) if early_exit is not None and protocol != "periodic"
                    else None),
        cycles=int(cycles), average=int(average),
        **control_attrs(control, protocol),
        voltage=float(model.voltage),
        duty=float(model.duty),
    ))


def to_dataset(res: CycleMetrics, coords: dict[str, np.ndarray], attrs: dict,
               variables: dict[str, tuple[str, str]] = VARIABLES) -> xr.Dataset:
    """Per-cell results (flat, C order over ``coords``; the attributes named in
    ``variables``) as a labelled Dataset."""
    shape = tuple(len(v) for v in coords.values())
    dims = tuple(coords)
    data = {}
    for name, (unit, desc) in variables.items():
        values = np.asarray(getattr(res, name)).reshape(shape)
        data[name] = xr.Variable(dims, values, attrs={"units": unit, "long_name": desc})
    data["steady"] = xr.Variable(dims, steady_cells(data["status"].values,
                                                    data["residual"].values),
                                 attrs={"units": STEADY[0], "long_name": STEADY[1]})
    coord_attrs = {**PARAMETER_UNITS, "f": ("Hz", "drive frequency"),
                   "M": ("kg", "payload mass"), "phase": ("rad", "phase of B")}
    ds = xr.Dataset(
        data,
        coords={k: xr.Variable((k,), np.asarray(v), attrs={
            "units": coord_attrs.get(k, ("", ""))[0],
            "long_name": coord_attrs.get(k, ("", ""))[1]}) for k, v in coords.items()},
        attrs={k: v for k, v in attrs.items() if v is not None},
    )
    attr_units = {"mass": "kg", "damping": "N s/m", "phase": "rad", "voltage": "V",
                  **{f"payload_{k}": u for k, (u, _) in PARAMETER_UNITS.items()}}
    ds.attrs["attribute_units"] = ", ".join(f"{k}: {u}" for k, u in attr_units.items()
                                            if k in ds.attrs)
    return ds
