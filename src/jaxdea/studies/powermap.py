"""Power maps: the papers' protocol over a whole [M, c, f(, phase)] grid, as one xarray Dataset.

Why this shape: paper 000's Figs 7-11 need P_out for every payload (M, c) and frequency f, i.e.
millions of independent cells. The cells are flattened in C order over (M, c, f, phase) and
run in chunks of one fixed size through :func:`jaxdea.protocol.run_protocol` (one compiled
executable for every chunk: the last chunk is padded by repeating its last cell, and the
padding is dropped). Chunks only bound memory and give resumable units of work; within a chunk
the cells are split evenly across all visible JAX devices (:mod:`jaxdea.sharding`; each device
runs its own lane pool on its slice). The per-cell arithmetic does not depend on which lane or
device runs a cell, so a map equals the same cells run by :func:`jaxdea.sweep`.

Protocols: ``paper`` (N cycles from rest per cell), ``continuation`` (each frequency starts
from the previous one's final state: a chain over f per payload and phase, so chunks and
device slices hold whole chains), ``periodic`` (periodic steady state, :mod:`jaxdea.steady`).

With ``store`` every finished chunk goes to disk at once (see :mod:`jaxdea.mapstore`), so a
killed run restarted with ``resume=True`` recomputes only the missing chunks and writes a store
identical to an uninterrupted run.

With ``client`` (a ``dask.distributed.Client``) the chunks run as tasks on the cluster's worker
processes, one JAX device each, and the workers write the parts (:mod:`.distributed`,
``docs/cluster.md``).
"""

from __future__ import annotations

import math
import os
import shutil
from contextlib import nullcontext
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import jax
import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from .._checks import (
    SweepError,
    check_choice,
    check_early_exit,
    check_int,
    check_protocol,
    check_unit_interval,
    finite_array,
)
from ..engine.batch import DIRECTIONS, EARLY_EXIT, PROTOCOLS, chain_successors
from ..engine.metrics import STATUS
from ..engine.precision import check_precision
from ..engine.protocols import STARTS, Protocol, as_keywords
from ..engine.sharding import on_accelerator
from ..engine.step_control import (
    StepControl,
    check_control,
    control_attrs,
    resolve_extrapolate,
)
from ..models.cone import Model
from ..payloads import parameters
from ..provenance import jaxdea_version
from .distributed import (
    ChunkJob,
    check_client,
    cluster_units,
    padded_cells,
    queue_order,
    run_chunk,
    run_on_cluster,
)
from .loadings import (
    DRIVES,
    Grid,
    anchor_payload,
    cell_payload,
    check_cone_model,
    check_model_ranges,
    check_payload,
    check_rest,
    drive_pattern,
    payload_parameters,
    warn_breakdown,
)
from .mapstore import (
    Parts,
    StoreLock,
    check_replaceable,
    check_store_path,
    parts_dir,
    previous_chunk_cells,
    write_store,
)
from .sweep import P_OUT_MEANING, map_variables, to_dataset

#: Default chunk size per device: large enough that the lane pools stay busy while a
#: low-frequency cell that never settles runs its 100 cycles (~3e5 steps at 1 Hz, against
#: ~5e3 for the mean cell), small enough for a fine progress bar and cheap resumes. Chunks
#: are equal (the last one is not mostly padding). Measured on 2 cores, 5 x 5 x 996 map:
#: 1190 / 1494 / 1536 trajectories/s with 1024 / 4096 / 8192 cells per device.
CHUNK_PER_DEVICE = 4096
#: Default chains per device in a continuation chunk: a chain runs its frequencies one
#: after another on one lane, so a chunk needs as many chains as the lane pool is wide.
CONTINUATION_CHAINS = 128
#: Default cells per device in each stage of a ``start="neighbour"`` chunk (whole masses: a
#: chunk is the smallest number of masses that gives this). A stage's chord calls run one
#: period of every cell, so they take at least the longest period of any cell; thousands of
#: cells per device keep the lanes busy meanwhile. Measured on 2 cores, DCDEA-LS, 50 c x 996
#: f: 0.32 ms per cell with 4 masses per chunk (1992 cells per device per stage), 0.30 ms
#: with 8, against 2.9 ms from rest.
NEIGHBOUR_STAGE_PER_DEVICE = 2048
#: The same two defaults on accelerators (:func:`jaxdea.engine.sharding.on_accelerator`),
#: where the lane pool is as wide as the chunk's slice of a device
#: (:func:`jaxdea.engine.batch.default_lanes`, shrinking as its cells finish): a narrow
#: pool's step costs as much as a wide one's there, so a chunk is large, short of losing the
#: progress bar and cheap resumes (the paper-size map: 10 chunks; a lane holds ~1 KiB,
#: estimated: three 112-byte DCDEA-LS states, its loading and the step's stages).
ACCELERATOR_CHUNK_PER_DEVICE = 2**18
ACCELERATOR_STAGE_PER_DEVICE = 2**15
_BYTES_PER_CELL = 8 * len(map_variables("neighbour"))


def _axis(name: str, values, *, positive: bool = False, nonnegative: bool = False) -> np.ndarray:
    """A validated, 1-D, strictly increasing axis."""
    arr = finite_array(name, values, positive=positive, nonnegative=nonnegative)
    if arr.ndim != 1:
        raise SweepError(f"{name} must be a 1-D axis, got shape {arr.shape}")
    if arr.size > 1 and not np.all(np.diff(arr) > 0):
        raise SweepError(f"{name} must be strictly increasing (sorted, no repeated values)")
    return arr


def _available_memory() -> int:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def _check_size(shape: tuple[int, ...], dims: tuple[str, ...], store: Path | None) -> None:
    """Fail before computing when the results would not fit in memory or on disk."""
    n = math.prod(shape)
    need = n * _BYTES_PER_CELL
    grid = " x ".join(f"{d} {s}" for d, s in zip(dims, shape))
    args = "/".join({"M": "mass", "c": "damping", "f": "freq"}.get(d, f"payload.{d}")
                    if d != "phase" else d for d in dims)
    mem = _available_memory()
    if 3 * need > mem:  # results + Dataset copy + writer buffers
        raise SweepError(f"grid {grid} = {n} cells needs ~{3 * need / 2**30:.1f} GiB of memory "
                         f"for its results, {mem / 2**30:.1f} GiB available: shrink {args}")
    if store is not None:
        free = shutil.disk_usage(store.parent if store.parent.exists() else Path.cwd()).free
        if 2 * need > free:  # chunk parts + final store
            raise SweepError(f"grid {grid} = {n} cells needs ~{2 * need / 2**30:.1f} GiB on "
                             f"disk, {free / 2**30:.1f} GiB free at {store.parent}: shrink {args}")


def _model_settings(model: Model) -> dict[str, Any]:
    """Every parameter of the model as ``{path: value}`` (JSON-able, exact floats)."""
    leaves = jax.tree_util.tree_flatten_with_path(model)[0]
    out = {"name": model.name}
    for path, leaf in leaves:
        try:
            out[jax.tree_util.keystr(path)] = np.asarray(leaf, dtype=float).tolist()
        except (TypeError, ValueError):
            out[jax.tree_util.keystr(path)] = repr(leaf)
    return out


_run_chunk = run_chunk  # one chunk in this process (tests replace it)


def reduce_over_f(ds: xr.Dataset) -> xr.Dataset:
    """P_max and f_at_P_max over f, among cells with status 0 that are steady (NaN where none
    is; a Dataset without ``steady``, e.g. an older store, counts every cell as steady)."""
    ok = ds["status"] == 0
    if "steady" in ds:
        ok = ok & ds["steady"]
    p = ds["P_out"].where(ok, -np.inf)
    i = p.argmax("f")
    any_ok = ok.any("f")
    p_max = ds["P_out"].isel(f=i).where(any_ok)
    f_at = ds["f"].isel(f=i).where(any_ok).drop_vars("f", errors="ignore")
    p_max = p_max.drop_vars("f", errors="ignore")
    ds["P_max"] = p_max.assign_attrs(
        units="W", long_name="max over f of P_out among cells with status 0 and steady "
                             "(NaN: none is)")
    ds["f_at_P_max"] = f_at.assign_attrs(units="Hz", long_name="frequency of P_max")
    return ds


def chunk_target(protocol: str, start: str, shape: tuple[int, ...], devices: tuple,
                 chunk_cells: int | None) -> tuple[int, int, tuple[int, int] | None]:
    """How a map of ``shape`` is cut into chunks on ``devices`` (empty: a cluster's workers).

    Returns ``(unit, target, chain)``: chunks hold whole ``unit`` s of cells (a payload's
    frequency chains on every device for continuation, whole masses for warm starts, one
    cell per device otherwise), about ``target`` cells each (``chunk_cells``, else the
    defaults above, larger on accelerators), and ``chain`` is the warm-start chain's
    ``(stages, cells per stage and mass)`` (None without warm starts)."""
    n_dev = max(len(devices), 1)
    n_f, n_rest = shape[2], (shape[3] if len(shape) == 4 else 1)
    wide = bool(devices) and on_accelerator(devices)
    if protocol == "continuation":  # whole chains (all f of a payload and phase) per device
        return n_f * n_rest * n_dev, chunk_cells or CONTINUATION_CHAINS * n_f * n_dev, None
    if start == "neighbour":  # whole masses: every stage of the chain over axis 1 in a chunk
        stage = ACCELERATOR_STAGE_PER_DEVICE if wide else NEIGHBOUR_STAGE_PER_DEVICE
        return (shape[1] * n_f * n_rest, chunk_cells or stage * n_dev * shape[1],
                (shape[1], n_f * n_rest))
    per_device = ACCELERATOR_CHUNK_PER_DEVICE if wide else CHUNK_PER_DEVICE
    return n_dev, chunk_cells or per_device * n_dev, None


def powermap(model: Model, *, mass, damping=None, freq, payload=None, phase=None,
             drive: str = "A",
             protocol: str | Protocol = "paper", cycles: int = 100, average: int = 5,
             direction: str = "forward", tol: float = 1e-6, start: str = "rest",
             early_exit: float | None = EARLY_EXIT, control: StepControl = StepControl(),
             chunk_cells: int | None = None,
             store: str | os.PathLike | None = None, resume: bool = False,
             progress: bool = True, client=None) -> xr.Dataset:
    """Power map of ``model`` over payload mass x damping x frequency (x phase).

    ``mass`` (kg, >= 0), ``damping`` (N s/m, >= 0), ``freq`` (Hz, > 0): 1-D increasing axes.
    ``payload``: a payload law (:class:`jaxdea.Drag`, :class:`jaxdea.Elastic`,
    :class:`jaxdea.Gravity` or a sum of them) instead of ``damping``, with exactly one of its
    parameters a 1-D increasing axis, e.g. ``Drag(quadratic=[...])``: the map's dims are then
    ``(M, quadratic, f[, phase])`` (its other parameters are scalars, in the attrs; the law's
    own mass must be 0 or the one ``mass`` value).
    ``phase`` (rad, in [0, 2 pi)): optional axis of B's delay, only with ``drive="both"``.
    ``protocol="paper"``: ``cycles`` periods from rest per cell, mean of the last ``average``.
    ``"continuation"``: the same, but each frequency starts from the previous frequency's
    final state (``direction="forward"``: up the f axis, as paper 000 swept; ``"backward"``:
    down it; compare both to expose jumps). ``"periodic"``: periodic steady state per cell
    to tolerance ``tol`` (:mod:`jaxdea.steady`; ``cycles``/``average`` unused).
    ``start`` (periodic only): ``"rest"``, every cell from rest; ``"neighbour"``, each cell
    from its neighbour's converged orbit along the second axis (c or the law's axis), from
    the heaviest load down, by chord iterations (:mod:`jaxdea.engine.warmstart`; chunks are
    then whole masses, :data:`NEIGHBOUR_STAGE_PER_DEVICE`). Where responses coexist it
    reports the branch continued from the heavier loads, not necessarily the from-rest one.
    ``early_exit``: paper and continuation cells stop once periodic to this tolerance
    (:data:`jaxdea.sweep.EARLY_EXIT`; ``None``: every cell runs all ``cycles``).
    The cells of each chunk are split over all JAX devices (:func:`jaxdea.use_cpu_cores`
    makes one per CPU core; the CLI does that).
    ``chunk_cells``: cells per compiled call (rounded up to a multiple of the device count,
    and for continuation to whole frequency chains per device; default: equal chunks of at
    most :data:`CHUNK_PER_DEVICE` cells, or for continuation :data:`CONTINUATION_CHAINS`
    chains, per device). ``store`` (``.zarr`` or ``.nc``): write each finished chunk to
    ``<store>.parts`` and the final Dataset to ``store``; ``resume=True`` reuses the
    finished chunks of an interrupted run with identical settings. ``progress``: tqdm bar
    over chunks.
    ``client``: a ``dask.distributed.Client``: run one task per chunk on its workers (one
    JAX device per worker process; with ``store`` each worker writes its chunk's part, the
    caller assembles the store), queued lowest frequency first. Default chunks there:
    about :data:`jaxdea.studies.distributed.CHUNKS_PER_WORKER` per worker, at least
    :data:`~jaxdea.studies.distributed.MIN_CLUSTER_CHUNK` and at most
    :data:`CHUNK_PER_DEVICE` cells (``docs/cluster.md``). ``resume=True`` without
    ``chunk_cells`` keeps the interrupted run's chunk size, whatever the device or worker
    count now.

    Returns a Dataset with dims (M, c, f[, phase]) (with ``payload``: (M, its axis parameter,
    f[, phase])) and variables P_out, P_in, P_in_signed,
    efficiency, amplitude, v_rms, status (0 = ok, see :data:`jaxdea.STATUS`), steps, residual
    (periodicity residual of the last cycle), cycles_run, steady (false where the last cycles
    are not periodic, :data:`jaxdea.engine.metrics.STEADY_RESIDUAL`), with
    ``start="neighbour"`` coexist (true where another stable orbit was found from the
    neighbouring mass's or by continuation along f,
    :func:`jaxdea.engine.coexist.coexisting`), plus P_max and
    f_at_P_max (reduced over f, among cells with status 0 that are steady).
    ``attrs["chunks_computed"]`` and ``attrs["chunks_reused"]`` count the work done by this
    call (not written to the store).
    All arguments are checked before any computation (:class:`SweepError` naming the argument).

    ``protocol`` may also be a protocol object (:class:`jaxdea.Paper`,
    :class:`jaxdea.Continuation`, :class:`jaxdea.Periodic`): its settings are then used, and
    ``cycles``, ``average``, ``direction``, ``tol`` and ``early_exit`` must stay at their
    defaults. The map equals the string form's with the same settings, attrs included.
    """
    # ---- validation (nothing is computed before all of this passes) -------------------
    check_cone_model(model)
    n_workers = check_client(client) if client is not None else 0
    protocol, (cycles, average, early_exit, direction, tol, start) = as_keywords(
        protocol, cycles=cycles, average=average, early_exit=early_exit, direction=direction,
        tol=tol, start=start)
    check_choice("protocol", protocol, PROTOCOLS)
    check_choice("start", start, STARTS)
    if start != "rest" and protocol != "periodic":
        raise SweepError(f"start = {start!r} warm-starts the periodic solve; it needs "
                         f"protocol='periodic', got protocol={protocol!r}")
    check_choice("drive", drive, DRIVES)
    check_choice("direction", direction, DIRECTIONS)
    check_unit_interval("tol", tol)
    law_axis = "c"
    if payload is None:
        axes = {"M": _axis("mass", mass, nonnegative=True),
                "c": _axis("damping", damping, nonnegative=True)}
    else:
        check_payload(None if mass is None else np.atleast_1d(mass), damping, payload,
                      axes=True)
        varied = {k: v for k, v in parameters(payload).items() if np.ndim(v) == 1}
        if not varied:
            raise SweepError("payload: a map needs one law parameter as a 1-D axis, e.g. "
                             "jaxdea.Drag(quadratic=[0.1, 1.0, 10.0]) (a single value: [x])")
        (law_axis, values), = varied.items()
        axes = {"M": _axis("mass", mass, nonnegative=True),
                law_axis: _axis(f"payload.{law_axis}", values)}  # its range: check_payload
    axes["f"] = _axis("freq", freq, positive=True)
    if phase is not None:
        if drive != "both":
            raise SweepError(f"phase is only used with drive='both' (B delayed against A); "
                             f"got drive={drive!r}: drop phase or use drive='both'")
        axes["phase"] = _axis("phase", phase)
        bad = axes["phase"][(axes["phase"] < 0) | (axes["phase"] >= 2 * math.pi)]
        if bad.size:
            raise SweepError(f"phase = {float(bad[0])!r} rad is outside the allowed range "
                             "[0, 2 pi)")
    phase_values = axes.get("phase", np.zeros(1))
    patterns = [drive_pattern(model, drive, float(p)) for p in phase_values]
    check_protocol(cycles, average)
    check_early_exit(early_exit)
    early_exit = None if early_exit is None or protocol == "periodic" else float(early_exit)
    check_control(control)
    check_precision(control, protocol, early_exit)
    if chunk_cells is not None:
        check_int("chunk_cells", chunk_cells, 1)
    store = check_store_path(store) if store is not None else None
    if store is not None:
        check_replaceable(store)  # never write over a file or folder jaxdea did not write
    if resume and store is None:
        raise SweepError("resume=True needs a store (the path of the interrupted run's output)")
    if resume and store.exists() and not parts_dir(store).exists():
        # a finished map: nothing was interrupted, and recomputing would replace it unasked
        raise SweepError(f"nothing to resume: {store} is a finished map (no {store.name}.parts "
                         "of an interrupted run beside it); run without --resume "
                         "(resume=False) to recompute and replace it, or choose another path")
    shape = tuple(a.size for a in axes.values())
    _check_size(shape, tuple(axes), store)
    check_model_ranges(model)  # a model edited in code, as a config would be
    warn_breakdown(model)
    if payload is not None:  # the rest state of every (M, law value) exists
        payload = anchor_payload(model, payload)
        m, v = (a.ravel() for a in np.meshgrid(axes["M"], axes[law_axis], indexing="ij"))
        check_rest(model, cell_payload(payload, m, m.size, **{law_axis: v}))

    # ---- chunking -----------------------------------------------------------------------
    devices = tuple(jax.devices()) if client is None else ()  # cluster: one per worker
    n_cells = math.prod(shape)
    control = resolve_extrapolate(control, n_cells, early_exit)  # the map's, not a chunk's
    successor = None
    n_f, n_rest = shape[2], (shape[3] if len(shape) == 4 else 1)
    unit, target, chain = chunk_target(protocol, start, shape, devices, chunk_cells)
    units = -(-n_cells // unit)
    per_chunk = min(-(-int(target) // unit), units)  # units per chunk: no more than the grid
    if chunk_cells is None and client is not None:
        per_chunk = cluster_units(units, unit, n_workers, int(target))
    if chunk_cells is None:  # equal chunks: the last one is not mostly padding
        per_chunk = -(-units // -(-units // per_chunk))
    old = previous_chunk_cells(store) if resume and chunk_cells is None else None
    if old is not None and old % unit == 0:  # resume keeps the interrupted run's chunks
        per_chunk = min(old // unit, units)
    chunk = per_chunk * unit
    if protocol == "continuation":
        successor = chain_successors(n_f, n_rest, direction, per_chunk)
    n_chunks = -(-n_cells // chunk)
    grid = Grid(axes=axes, shape=shape,
                 amplitude=np.stack([on * float(model.voltage) for on, _ in patterns]),
                 phases=np.stack([ph for _, ph in patterns]), duty=float(model.duty),
                 payload=payload, law_axis=law_axis)
    attrs = dict(model=model.name, drive=drive, protocol=protocol, cycles=int(cycles),
                 average=int(average),
                 direction=direction if protocol == "continuation" else None,
                 tol=float(tol) if protocol == "periodic" else None, early_exit=early_exit,
                 **({"start": start} if protocol == "periodic" else {}),
                 **control_attrs(control, protocol),
                 dt_max=float(control.dt_max),
                 max_steps=int(control.max_steps), voltage=float(model.voltage),
                 duty=float(model.duty), jaxdea_version=jaxdea_version(),
                 **(payload_parameters(payload) if payload is not None else {}),
                 P_out_meaning=P_OUT_MEANING)
    if drive == "both" and phase is None:
        attrs["phase"] = 0.0

    # one run per store (a second is refused with a clear message); released on Ctrl-C
    with StoreLock(store) if store is not None else nullcontext():
        parts, done = None, set()
        if store is not None:
            settings = dict(attrs, config=_model_settings(model), chunk_cells=chunk,
                            axes={k: v.tolist() for k, v in axes.items()})
            parts = Parts(store, settings, n_chunks)
            done = parts.open(resume)

        # ---- run ----------------------------------------------------------------------------
        names = map_variables(start)
        dtypes = {"status": np.int32, "steps": np.int32, "cycles_run": np.int32,
                  "coexist": bool}
        results = {k: np.empty(n_cells, dtype=dtypes.get(k, float)) for k in names}
        computed = reused = 0
        todo = set(range(n_chunks))
        bar = tqdm(total=n_chunks - len(done), desc="powermap chunks", unit="chunk",
                   disable=not progress, postfix={"reused": len(done)} if done else None)
        run = dict(protocol=protocol, successor=successor, cycles=int(cycles),
                   average=int(average), control=control, tol=float(tol), early_exit=early_exit,
                   chain=chain)
        job = ChunkJob(model=model, grid=grid, chunk=chunk, n_cells=n_cells, run=run, parts=parts)
        try:
            for i in range(n_chunks):
                lo, hi = i * chunk, min((i + 1) * chunk, n_cells)
                got = parts.load(i, hi - lo, names, cells=(lo, hi)) if i in done else None
                if got is not None:
                    reused += 1
                elif client is not None:  # computed below, on the cluster
                    bar.total += i in done
                    continue
                else:
                    if i in done:  # unreadable part: count it as computed work
                        bar.total += 1
                    out = _run_chunk(model, grid.loadings(padded_cells(lo, chunk, hi)),
                                     devices, real=hi - lo, **run)
                    got = {k: v[: hi - lo] for k, v in out.items()}
                    if parts is not None:
                        parts.save(i, got, cells=(lo, hi))
                    computed += 1
                    bar.update(1)
                for k in names:
                    results[k][lo:hi] = got[k]
                todo.discard(i)
            if client is not None and todo:
                computed = run_on_cluster(client, job, queue_order(todo, job, n_f, n_rest),
                                          results, on_done=lambda: bar.update(1))
        finally:
            bar.close()

        # ---- assemble -----------------------------------------------------------------------
        ds = to_dataset(SimpleNamespace(**results), axes, attrs, names)
        ds.attrs["status_codes"] = "; ".join(f"{k} = {v}" for k, v in STATUS.items())
        ds = reduce_over_f(ds)
        if store is not None:
            write_store(ds, store)
            parts.remove()
        ds.attrs["chunks_computed"] = computed
        ds.attrs["chunks_reused"] = reused
        return ds
