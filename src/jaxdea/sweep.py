"""Frequency sweeps of a configured model: the papers' protocol over an f axis, as xarray.

The whole frequency axis is one jitted computation (:func:`jaxdea.protocol.run_protocol`);
there is no Python loop over frequencies.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr

from .actuators.base import Loading
from .config import ConfigError, Model
from .payloads import LinearViscous
from .protocol import STATUS, CycleMetrics, StepControl, run_protocol
from .sharding import cell_sharded
from .signals import SquareWave

DRIVES = ("A", "B", "both")
#: Protocols: the papers' N cycles from rest per cell; frequency continuation (each f starts
#: from the previous f's final state); periodic steady state (settle, then Newton shooting).
PROTOCOLS = ("paper", "continuation", "periodic")
DIRECTIONS = ("forward", "backward")

#: Units and descriptions of the per-cell outputs.
VARIABLES = {
    "P_out": ("W", "mean payload power over the averaging window (paper 000 eq 19)"),
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

_run = eqx.filter_jit(run_protocol)


@eqx.filter_jit
def _rest_states(actuator, n: int):
    """The rest state (static equilibrium) repeated for ``n`` cells (compiled once)."""
    rest = actuator.initial_state()
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), rest)


class SweepError(ValueError):
    """Bad sweep arguments (checked before any computation)."""


def _finite_array(name: str, value: Any, *, positive: bool = False,
                  nonnegative: bool = False) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.size == 0:
        raise SweepError(f"{name} is empty: give at least one value")
    if not np.all(np.isfinite(arr)):
        raise SweepError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise SweepError(f"{name} must be > 0 (allowed range (0, inf)), got min {arr.min():g}")
    if nonnegative and np.any(arr < 0):
        raise SweepError(f"{name} must be >= 0 (allowed range [0, inf)), got min {arr.min():g}")
    return arr


def drive_pattern(model: Model, drive: str, phase: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-membrane amplitude multipliers and phases for a drive case.

    ``"A"``: membrane A only (the single cone's one membrane is "A"); ``"B"``: membrane B only;
    ``"both"``: A and B, B delayed by ``phase`` rad (0 = in-phase, pi = antiphase).
    """
    names = model.actuator.membrane_names
    if drive not in DRIVES:
        raise SweepError(f"drive = {drive!r} must be one of {', '.join(DRIVES)}")
    if drive != "A" and len(names) == 1:
        raise SweepError(f"drive = {drive!r}: {model.name or 'this model'} has one membrane; "
                         "use drive='A'")
    if not math.isfinite(phase):
        raise SweepError(f"phase must be finite (allowed range [0, 2 pi)), got {phase!r}")
    if not 0.0 <= phase < 2.0 * math.pi:
        raise SweepError(f"phase = {phase!r} rad is outside the allowed range [0, 2 pi)")
    on = np.array([drive in ("both", n) for n in names], dtype=float)
    phases = np.where(np.array(names) == "B", phase if drive == "both" else 0.0, 0.0)
    return on, phases


def make_loadings(model: Model, mass, damping, freq, drive: str = "A",
                  phase: float = 0.0) -> Loading:
    """Loadings for the broadcast of ``mass``, ``damping``, ``freq`` (flattened, C order)."""
    mass = _finite_array("mass", mass, nonnegative=True)
    damping = _finite_array("damping", damping, nonnegative=True)
    freq = _finite_array("freq", freq, positive=True)
    on, phases = drive_pattern(model, drive, float(phase))
    m, c, f = (a.ravel() for a in np.broadcast_arrays(mass, damping, freq))
    n = f.size
    amp = jnp.asarray(on)[None, :] * model.voltage
    return Loading(
        drive=SquareWave(
            amplitude=jnp.broadcast_to(amp, (n, on.size)),
            frequency=jnp.asarray(f),
            duty=jnp.broadcast_to(model.duty, (n,)),
            phase=jnp.broadcast_to(jnp.asarray(phases), (n, on.size)),
        ),
        payload=LinearViscous(mass=jnp.asarray(m), damping=jnp.asarray(c)),
    )


def check_protocol(cycles: int, average: int) -> None:
    for name, v in (("cycles", cycles), ("average", average)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise SweepError(f"{name} must be an integer >= 1, got {v!r}")
    if average > cycles:
        raise SweepError(f"average = {average} must be <= cycles = {cycles}")


#: Early exit of the paper and continuation protocols: a cell stops once its trajectory is
#: periodic to this scaled residual (corrected for the observed contraction per cycle), since
#: its remaining cycles would repeat the last one; its metrics are then over that last cycle.
#: At 1e-8 the metrics equal the full N-cycle run's to ~1e-7 relative (tests/test_protocols;
#: 2e-9 at 1e-10, for 11 % more steps), far below the integration error (~5e-5 against LSODA
#: at rtol 1e-9). ``None`` runs every cell for all N cycles.
EARLY_EXIT = 1e-8


def check_early_exit(early_exit) -> None:
    if early_exit is None:
        return
    if isinstance(early_exit, bool) or not isinstance(early_exit, (int, float, np.floating)) \
            or not (math.isfinite(early_exit) and 0 < early_exit < 1):
        raise SweepError(f"early_exit = {early_exit!r} must be None (run every cycle) or a "
                         "tolerance in the allowed range (0, 1)")


def _engine(actuator, loadings, successor, *, cycles, average, control, lanes, early_exit,
            driven=None):
    """The lane engine on one device's cells from rest (``successor``: local indices)."""
    return run_protocol(actuator, loadings, cycles=cycles, average=average, control=control,
                        lanes=lanes, successor=successor, settle=early_exit,
                        require_settled=False, driven=driven)


def driven_membranes(loadings: Loading) -> tuple[int, ...]:
    """The membranes with a non-zero drive amplitude in some cell (concrete loadings)."""
    amp = np.asarray(loadings.drive.amplitude)
    return tuple(int(j) for j in np.nonzero(np.any(amp != 0, axis=0))[0])


def _deal_slots(n: int, n_dev: int) -> np.ndarray:
    """Position in the dealt order of each of ``n_dev`` equal device slices' slots (values
    ``>= n`` are padding)."""
    local = -(-n // n_dev)
    return np.arange(local * n_dev).reshape(local, n_dev).T.ravel()


def dealt(n: int, n_dev: int) -> np.ndarray:
    """Cell order that deals ``n`` cells round-robin to ``n_dev`` equal device slices (padded
    by repeating the last cell): every device gets the same mix of frequencies."""
    return np.minimum(_deal_slots(n, n_dev), n - 1)


def schedule(freq: np.ndarray, n_dev: int) -> np.ndarray:
    """Queue order of a batch of independent cells: lowest frequency first, dealt
    round-robin over ``n_dev`` equal device slices (padded by repeating the last cell).

    Why: the lane pool drains its queue in order, and a batch takes as long as its slowest
    lane. The cells that can cost the most are the low-frequency ones (a cell that never
    settles runs all N cycles, and a cycle at f costs ~1/f of dt-limited steps: a 1 Hz cell
    may need ~3e5 steps where the mean cell needs ~6e3). Starting them first leaves only
    short cells for the end of the queue (longest-processing-time-first scheduling), so
    large lane pools stay busy until the batch is done.
    """
    order = np.argsort(np.asarray(freq), kind="stable")
    return order[dealt(order.size, n_dev)]


def run_cells(model: Model, loadings: Loading, *, cycles: int = 100, average: int = 5,
              control: StepControl = StepControl(), lanes: int | None = None,
              protocol: str = "paper", successor=None, tol: float = 1e-6,
              initial=None, early_exit: float | None = EARLY_EXIT,
              devices: tuple | None = None) -> CycleMetrics:
    """Run a protocol on a flat batch of cells (compiled calls cached per shape).

    ``"paper"``: ``cycles`` from rest, mean of the last ``average``. ``"continuation"``: the
    same, but cell ``i`` hands its final state to cell ``successor[i]`` (``n`` = none).
    ``"periodic"``: :func:`jaxdea.steady.periodic_cells` with tolerance ``tol`` (``cycles``
    and ``average`` unused). ``initial``: start states (leading axis = cells; default rest).
    ``early_exit``: :data:`EARLY_EXIT` (paper and continuation). ``devices``: JAX devices to
    split the cells over (default: the first device only). Paper runs from rest and periodic
    runs queue their cells lowest frequency first, dealt round-robin over the devices
    (:func:`schedule`); continuation runs and runs from given states use the first device
    only, in cell order (a continuation chain is sequential).
    """
    check_protocol(cycles, average)
    check_early_exit(early_exit)
    early_exit = None if early_exit is None else float(early_exit)
    if not isinstance(model, Model):
        raise ConfigError("model must come from jaxdea.load_config (a jaxdea.Model)")
    if protocol not in PROTOCOLS:
        raise SweepError(f"protocol = {protocol!r} must be one of {', '.join(PROTOCOLS)}")
    n = loadings.drive.frequency.shape[0]
    devices = tuple(devices or jax.devices()[:1])
    local = -(-n // len(devices))
    driven = driven_membranes(loadings)
    if protocol == "periodic":
        from .steady import periodic_cells
        return _dealt_run(lambda ld: periodic_cells(
            model.actuator, ld, tol=tol, control=control, lanes=lanes or default_lanes(local),
            devices=devices, driven=driven), loadings, n, devices)
    if protocol == "continuation" and successor is None:
        raise SweepError("protocol='continuation' needs the successor of each cell")
    if protocol == "paper" and initial is None:  # independent cells: schedule them
        lanes = lanes or default_lanes(local)
        if len(devices) > 1:
            run = lambda ld: cell_sharded(_engine, devices)(  # noqa: E731
                model.actuator, ld, jnp.full(local * len(devices), local, jnp.int32),
                cycles=int(cycles), average=int(average), control=control, lanes=lanes,
                early_exit=early_exit, driven=driven)
        else:
            run = lambda ld: _run_engine(model, ld, cycles, average, control, lanes,  # noqa
                                         None, np.full(n, n), early_exit, driven)
        return _dealt_run(run, loadings, n, devices)
    if protocol == "paper" or successor is None:
        successor = np.full(n, n)
    lanes = lanes or default_lanes(chain_heads(successor))  # a chain is busy on one lane
    return _run_engine(model, loadings, cycles, average, control, lanes, initial, successor,
                       early_exit, driven)


def _run_engine(model, loadings, cycles, average, control, lanes, initial, successor,
                early_exit, driven=None):
    """The lane engine on one device. One compiled engine for paper and continuation runs of
    any cycle count: the start states, successors and cycle counts are all arguments, not
    constants."""
    n = loadings.drive.frequency.shape[0]
    if initial is None:
        initial = _rest_states(model.actuator, n)
    return _run(model.actuator, loadings, cycles=jnp.asarray(cycles, jnp.int32),
                average=jnp.asarray(average, jnp.int32), control=control, lanes=lanes,
                initial=initial, successor=jnp.asarray(successor, jnp.int32),
                settle=early_exit, require_settled=False, driven=driven)


def _dealt_run(run, loadings: Loading, n: int, devices: tuple):
    """``run(loadings)`` on the ``n`` independent cells in :func:`schedule` order (lowest
    frequency first, dealt round-robin over ``devices``), its per-cell results put back in
    cell order."""
    take = lambda tree, idx: jax.tree_util.tree_map(lambda a: a[idx], tree)  # noqa: E731
    order = schedule(np.asarray(loadings.drive.frequency), len(devices))
    real = _deal_slots(n, len(devices)) < n  # the slots that are not padding
    where = np.empty(n, dtype=np.int64)  # slot of each cell
    where[order[real]] = np.nonzero(real)[0]
    return take(run(take(loadings, order)), where)


def chain_successors(n_f: int, n_rest: int = 1, direction: str = "forward",
                     n_blocks: int = 1) -> np.ndarray:
    """Successors for frequency continuation over cells laid out C-order as
    ``(blocks, f, rest)``: each cell hands on to the next (``"forward"``) or previous
    (``"backward"``) frequency with the same block and rest index; ``size`` marks "none"."""
    if direction not in DIRECTIONS:
        raise SweepError(f"direction = {direction!r} must be one of {', '.join(DIRECTIONS)}")
    size = n_blocks * n_f * n_rest
    idx = np.arange(size).reshape(n_blocks, n_f, n_rest)
    succ = np.full_like(idx, size)
    if direction == "forward":
        succ[:, :-1, :] = idx[:, 1:, :]
    else:
        succ[:, 1:, :] = idx[:, :-1, :]
    return succ.ravel()


def chain_heads(successor) -> int:
    """How many chains ``successor`` (:func:`chain_successors`; ``n`` = none) forms: the
    cells that are no cell's successor."""
    succ = np.asarray(successor)
    return int(succ.size - np.unique(succ[succ < succ.size]).size)


def default_lanes(n_cells: int) -> int:
    """Lane-pool size of a batch of ``n_cells`` cells on one device: 128, or all the cells.

    Measured on a 2-core CPU (one device per core): a step of 128 lanes costs ~43 us, of 32
    lanes ~15 us, of 8 lanes ~6.5 us, of one lane ~4 us (per-step overhead), so wide pools
    are ~1.4x cheaper per cell-step than 32 lanes; 256 lanes are slower again (cache). Wide
    pools pay off only when they stay busy to the end: cells are queued lowest frequency
    first (:func:`schedule`) and the batch ends in smaller pools
    (:func:`jaxdea.protocol.lane_pools`). The 8 x 8 x 64 bench map runs 1.5x faster with 128
    lanes than with 32, the 996-f sweep with its early exit 1.5x (strict: the same).
    """
    return int(min(n_cells, 128))


def sweep(model: Model, *, mass: float, damping: float, freq, drive: str = "A",
          phase: float = 0.0, cycles: int = 100, average: int = 5,
          control: StepControl = StepControl(), lanes: int | None = None,
          protocol: str = "paper", direction: str = "forward",
          tol: float = 1e-6, early_exit: float | None = EARLY_EXIT) -> xr.Dataset:
    """Frequency response of ``model``.

    ``mass`` (kg) and ``damping`` (N s/m) of the payload, ``freq`` (Hz, 1-D), ``drive`` one of
    ``"A"``, ``"B"``, ``"both"``; ``phase`` (rad) of B relative to A when both are driven.
    ``protocol="paper"`` (default): each frequency runs ``cycles`` periods from rest; metrics
    average the last ``average``. ``"continuation"``: the same, but each frequency starts from
    the previous one's final state, in ``freq`` order (``direction="backward"``: from the
    highest frequency down) — paper 000's forward sweep, and the backward one that exposes
    jumps. ``"periodic"``: the periodic steady state to tolerance ``tol``
    (:mod:`jaxdea.steady`). ``early_exit``: paper and continuation cells stop once periodic
    to this tolerance (:data:`EARLY_EXIT`; ``None``: every cell runs all ``cycles``). The
    cells are split over all JAX devices (:func:`jaxdea.use_cpu_cores` makes one per CPU
    core). Returns a Dataset with dimension ``f`` and variables P_out, P_in,
    P_in_signed, efficiency, amplitude, v_rms, status, steps, residual, cycles_run (units in
    attrs).
    """
    if protocol not in PROTOCOLS:
        raise SweepError(f"protocol = {protocol!r} must be one of {', '.join(PROTOCOLS)}")
    if direction not in DIRECTIONS:
        raise SweepError(f"direction = {direction!r} must be one of {', '.join(DIRECTIONS)}")
    if not (math.isfinite(tol) and 0 < tol < 1):
        raise SweepError(f"tol = {tol!r} is outside the allowed range (0, 1)")
    check_early_exit(early_exit)
    freq = _finite_array("freq", freq, positive=True)
    if freq.ndim != 1:
        raise SweepError(f"freq must be 1-D, got shape {freq.shape}")
    for name, v in (("mass", mass), ("damping", damping)):
        if np.ndim(v) != 0:
            raise SweepError(f"{name} must be a scalar for a sweep (use powermap for grids)")
    loadings = make_loadings(model, mass, damping, freq, drive, phase)
    successor = chain_successors(freq.size, direction=direction)
    devices = tuple(jax.devices())
    res = run_cells(model, loadings, cycles=cycles, average=average, control=control,
                    lanes=lanes, protocol=protocol, successor=successor, tol=tol,
                    early_exit=early_exit, devices=devices)
    return to_dataset(res, {"f": freq}, attrs=dict(
        model=model.name, drive=drive, phase=float(phase), mass=float(mass),
        damping=float(damping), protocol=protocol,
        direction=direction if protocol == "continuation" else None,
        tol=float(tol) if protocol == "periodic" else None,
        early_exit=(float(early_exit) if early_exit is not None and protocol != "periodic"
                    else None),
        cycles=int(cycles), average=int(average),
        rtol=control.rtol, voltage=float(model.voltage), duty=float(model.duty),
    ))


def to_dataset(res: CycleMetrics, coords: dict[str, np.ndarray], attrs: dict) -> xr.Dataset:
    """Per-cell results (flat, C order over ``coords``) as a labelled Dataset."""
    shape = tuple(len(v) for v in coords.values())
    dims = tuple(coords)
    data = {}
    for name, (unit, desc) in VARIABLES.items():
        values = np.asarray(getattr(res, name)).reshape(shape)
        data[name] = xr.Variable(dims, values, attrs={"units": unit, "long_name": desc})
    coord_attrs = {"f": ("Hz", "drive frequency"), "M": ("kg", "payload mass"),
                   "c": ("N s/m", "payload damping"), "phase": ("rad", "phase of B")}
    ds = xr.Dataset(
        data,
        coords={k: xr.Variable((k,), np.asarray(v), attrs={
            "units": coord_attrs.get(k, ("", ""))[0],
            "long_name": coord_attrs.get(k, ("", ""))[1]}) for k, v in coords.items()},
        attrs={k: v for k, v in attrs.items() if v is not None},
    )
    attr_units = {"mass": "kg", "damping": "N s/m", "phase": "rad", "voltage": "V"}
    ds.attrs["attribute_units"] = ", ".join(f"{k}: {u}" for k, u in attr_units.items()
                                            if k in ds.attrs)
    return ds
