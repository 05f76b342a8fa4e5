"""Batches of independent cells on the lane engine: scheduling, device dealing, protocols.

:func:`run_cells` runs a flat batch of cells (any mix of frequencies, payloads, phases)
through one of the protocols (:data:`PROTOCOLS`) on one or several JAX devices. Independent
cells are queued lowest frequency first and dealt round-robin over the devices
(:func:`schedule`); frequency-continuation chains (:func:`chain_successors`) run on one
device in cell order.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import ConfigError, SweepError, check_choice, check_early_exit, check_protocol
from ..models.cone import Loading, Model
from .lane_state import rest_states
from .lanes import run_protocol
from .metrics import CycleMetrics
from .paper import run_paper
from .precision import check_precision
from .protocols import (
    DIRECTIONS,
    EARLY_EXIT,
    PROTOCOLS,
    Protocol,
    as_keywords,
    check_rest_start,
)
from .sharding import cell_sharded, on_accelerator
from .step_control import StepControl, check_control, resolve_extrapolate

_run = eqx.filter_jit(run_protocol)

_run_paper = eqx.filter_jit(run_paper)

_rest_states = eqx.filter_jit(rest_states)


#: Widest lane pool on a CPU device (:func:`default_lanes`): measured on 2 cores,
#: ``bench/NOTES.md``.
CPU_LANES = 128

#: Smallest per-device batch of independent cells (:func:`batch_cells`).
SMALLEST_BATCH = 8


def batch_cells(local: int) -> int:
    """Cells per device that a batch of ``local`` independent cells per device is run as:
    ``local`` padded (with copies of its highest-frequency cell, :func:`dealt`) up to a
    power of two from :data:`SMALLEST_BATCH` to :data:`CPU_LANES`; above that, ``local``.

    Why: a compiled engine is specific to its batch's shape, and compiling one costs 5-15 s
    on a CPU where running a small sweep costs less. With the padding, sweeps of 3 or 7
    frequencies, or 9 to 16 (per device), share one compiled program (in memory, and
    through the on-disk compile cache across runs). A batch this small fits one default
    lane pool at once, so every cell still has its own lane from its start; cells are
    independent, so a cell's numbers do not depend on the batch (1e-12 in
    ``tests/test_scheduling.py``), and the padding's copies finish with the cell they copy.
    Larger batches (power-map chunks) keep their own size: their shapes are fixed by the
    chunking, and padding them would be work. What it saves is measured in
    ``bench/NOTES.md``.

    **Arguments:**

    - `local`: the batch's cells per device.

    **Returns:**

    The cells per device the batch runs as (``>= local``).
    """
    if local > CPU_LANES:
        return int(local)
    return max(SMALLEST_BATCH, 1 << (int(local) - 1).bit_length())


def run_from_rest(actuator, loadings, successor, *, cycles, average, control, lanes,
                  early_exit, driven=None):
    """The lane engine on one device's cells from rest (``successor``: local indices)."""
    return run_protocol(actuator, loadings, cycles=cycles, average=average, control=control,
                        lanes=lanes, successor=successor, settle=early_exit,
                        require_settled=False, driven=driven)


def driven_membranes(loadings: Loading) -> tuple[int, ...]:
    """The membranes with a non-zero drive amplitude in some cell (concrete loadings)."""
    amp = np.asarray(loadings.drive.amplitude)
    return tuple(int(j) for j in np.nonzero(np.any(amp != 0, axis=0))[0])


def deal_slots(n: int, n_dev: int, local: int | None = None) -> np.ndarray:
    """Position in the dealt order of each of ``n_dev`` equal device slices' slots (values
    ``>= n`` are padding); ``local`` slots per device (default: as few as hold ``n``)."""
    local = local or -(-n // n_dev)
    return np.arange(local * n_dev).reshape(local, n_dev).T.ravel()


def dealt(n: int, n_dev: int, local: int | None = None) -> np.ndarray:
    """Cell order that deals ``n`` cells round-robin to ``n_dev`` equal device slices of
    ``local`` slots (:func:`deal_slots`; padded by repeating the last cell): every device
    gets the same mix of frequencies."""
    return np.minimum(deal_slots(n, n_dev, local), n - 1)


def schedule(freq: np.ndarray, n_dev: int, local: int | None = None) -> np.ndarray:
    """Queue order of a batch of independent cells: lowest frequency first, dealt
    round-robin over ``n_dev`` equal device slices of ``local`` slots (default: as few as
    hold the cells; padded by repeating the last cell, the highest frequency).

    Why: the lane pool drains its queue in order, and a batch takes as long as its slowest
    lane. The cells that can cost the most are the low-frequency ones (a cell that never
    settles runs all N cycles, and a cycle at f costs ~1/f of dt-limited steps: a 1 Hz cell
    may need ~3e5 steps where the mean cell needs ~6e3). Starting them first leaves only
    short cells for the end of the queue (longest-processing-time-first scheduling), so
    large lane pools stay busy until the batch is done.
    """
    order = np.argsort(np.asarray(freq), kind="stable")
    return order[dealt(order.size, n_dev, local)]


def scheduled_batches(cells: np.ndarray, size: int, freq: np.ndarray, n_dev: int):
    """The cells ``cells`` in batches of exactly ``size`` (a compiled call's shape), each in
    :func:`schedule` order (a generator).

    The last batch is padded by repeating its last cell. Yields ``(sub, real)``: the batch's
    cell indices and a bool per slot, true at one slot per distinct cell (pass it as
    ``active``: the padding slots are skipped at no cost)."""
    for lo in range(0, cells.size, size):
        part = cells[lo:lo + size]
        padded = np.concatenate([part, np.full(size - part.size, part[-1])])
        sub = padded[schedule(freq[padded], n_dev)]
        real = np.zeros(size, bool)
        real[np.unique(sub, return_index=True)[1]] = True
        yield sub, real


def run_cells(model: Model, loadings: Loading, *, cycles: int = 100, average: int = 5,
              control: StepControl = StepControl(), lanes: int | None = None,
              protocol: str | Protocol = "paper", successor=None, tol: float = 1e-6,
              initial=None, early_exit: float | None = EARLY_EXIT,
              devices: tuple | None = None) -> CycleMetrics:
    """Run a protocol on a flat batch of cells (compiled calls cached per shape).

    ``"paper"``: ``cycles`` from rest, mean of the last ``average``. ``"continuation"``: the
    same, but cell ``i`` hands its final state to cell ``successor[i]`` (``n`` = none).
    ``"periodic"``: :func:`jaxdea.engine.periodic.periodic_cells` with tolerance ``tol`` (``cycles``
    and ``average`` unused). ``initial``: start states (leading axis = cells; default rest).
    ``early_exit``: :data:`EARLY_EXIT` (paper and continuation). ``devices``: JAX devices to
    split the cells over (default: the first device only). Paper runs from rest and periodic
    runs queue their cells lowest frequency first, dealt round-robin over the devices
    (:func:`schedule`); continuation runs and runs from given states use the first device
    only, in cell order (a continuation chain is sequential).

    ``protocol`` may also be a protocol object (:class:`jaxdea.Paper`,
    :class:`jaxdea.Continuation`, :class:`jaxdea.Periodic`): its settings are then used,
    and ``cycles``, ``average``, ``tol`` and ``early_exit`` must stay at their defaults
    (:func:`jaxdea.engine.protocols.as_protocol`). A :class:`jaxdea.Continuation`'s chains
    are ``successor``, not its ``direction``.
    """
    check_rest_start(protocol, "run_cells (a flat batch of cells)")
    protocol, (cycles, average, early_exit, tol) = as_keywords(
        protocol, cycles=cycles, average=average, early_exit=early_exit, tol=tol)
    check_protocol(cycles, average)
    check_early_exit(early_exit)
    early_exit = None if early_exit is None else float(early_exit)
    check_control(control)
    check_precision(control, protocol, early_exit)
    control = resolve_extrapolate(control, loadings.drive.frequency.shape[0], early_exit)
    if not isinstance(model, Model):
        raise ConfigError("model must come from jaxdea.load_config (a jaxdea.Model)")
    check_choice("protocol", protocol, PROTOCOLS)
    n = loadings.drive.frequency.shape[0]
    devices = tuple(devices or jax.devices()[:1])
    local = batch_cells(-(-n // len(devices)))  # shared programs for small batches
    driven = driven_membranes(loadings)
    if protocol == "periodic":
        from .periodic import periodic_cells
        return _dealt_run(lambda ld: periodic_cells(
            model.actuator, ld, tol=tol, control=control,
            lanes=lanes or default_lanes(local, devices),
            devices=devices, driven=driven), loadings, n, devices, local)
    if protocol == "continuation" and successor is None:
        raise SweepError("protocol='continuation' needs the successor of each cell")
    if protocol == "paper" and initial is None:  # independent cells: schedule them
        lanes = lanes or default_lanes(local, devices)
        if len(devices) > 1:
            run = lambda ld: cell_sharded(run_paper, devices)(  # noqa: E731
                model.actuator, ld, cycles=int(cycles), average=int(average), control=control,
                lanes=lanes, settle=early_exit, driven=driven)
        else:
            run = lambda ld: _run_paper(  # noqa: E731
                model.actuator, ld, cycles=jnp.asarray(cycles, jnp.int32),
                average=jnp.asarray(average, jnp.int32), control=control, lanes=lanes,
                settle=early_exit, driven=driven)
        return _dealt_run(run, loadings, n, devices, local)
    if protocol == "paper" or successor is None:
        successor = np.full(n, n)
    # a chain is busy on one lane
    lanes = lanes or default_lanes(chain_heads(successor), devices)
    return _run_engine(model, loadings, cycles, average, control, lanes, initial, successor,
                       early_exit, driven)


def _run_engine(model, loadings, cycles, average, control, lanes, initial, successor,
                early_exit, driven=None):
    """The lane engine on one device. One compiled engine for paper and continuation runs of
    any cycle count: the start states, successors and cycle counts are all arguments, not
    constants."""
    if initial is None:
        initial = _rest_states(model.actuator, loadings)
    return _run(model.actuator, loadings, cycles=jnp.asarray(cycles, jnp.int32),
                average=jnp.asarray(average, jnp.int32), control=control, lanes=lanes,
                initial=initial, successor=jnp.asarray(successor, jnp.int32),
                settle=early_exit, require_settled=False, driven=driven)


def _dealt_run(run, loadings: Loading, n: int, devices: tuple, local: int):
    """``run(loadings)`` on the ``n`` independent cells in :func:`schedule` order (lowest
    frequency first, dealt round-robin over ``devices``, ``local`` slots each), its per-cell
    results put back in cell order.

    The results are reordered on the host: indexing arrays sharded over the devices with a
    replicated index compiles to a gather with an all-reduce across the devices, which XLA
    aborts the process on when one device's thread is 40 s late. Cells are independent, so
    nothing here needs a collective. (Traced results, one device only, stay traced.)"""
    order = schedule(np.asarray(loadings.drive.frequency), len(devices), local)
    real = deal_slots(n, len(devices), local) < n  # the slots that are not padding
    where = np.empty(n, dtype=np.int64)  # slot of each cell
    where[order[real]] = np.nonzero(real)[0]
    res = jax.tree_util.tree_map(_on_host, run(take_cells(loadings, order)))
    return jax.tree_util.tree_map(jnp.asarray, take_cells(res, where))


def take_cells(tree, idx):
    """The cells ``idx`` (an index array into the leading axis) of every leaf of ``tree``."""
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


def _on_host(a):
    """``a`` as a numpy array (each device's shard copied, no collective), unless traced."""
    return a if isinstance(a, jax.core.Tracer) else np.asarray(a)


def chain_successors(n_f: int, n_rest: int = 1, direction: str = "forward",
                     n_blocks: int = 1) -> np.ndarray:
    """Successors for frequency continuation over cells laid out C-order as
    ``(blocks, f, rest)``: each cell hands on to the next (``"forward"``) or previous
    (``"backward"``) frequency with the same block and rest index; ``size`` marks "none"."""
    check_choice("direction", direction, DIRECTIONS)
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


def default_lanes(n_cells: int, devices: tuple = ()) -> int:
    """Lane-pool size of a batch of ``n_cells`` cells on one device: on CPU devices 128, or
    all the cells; on accelerators all the cells (:func:`~jaxdea.engine.sharding.on_accelerator`).

    Wide pools are cheaper per cell-step (the per-step overhead is shared) but pay off only
    when they stay busy to the end: cells are queued lowest frequency first
    (:func:`schedule`) and the batch ends in smaller pools
    (:func:`jaxdea.engine.lanes.lane_pools`). Measurements: ``bench/NOTES.md``.

    **Arguments:**

    - `n_cells`: the batch's cells on one device.
    - `devices`: the devices the batch runs on (default: JAX's default devices).

    **Returns:**

    The widest pool's lanes.
    """
    if on_accelerator(devices):
        return int(n_cells)
    return int(min(n_cells, CPU_LANES))
