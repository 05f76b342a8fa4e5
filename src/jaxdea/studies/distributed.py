"""Power-map chunks as tasks, in this process or on a Dask distributed cluster.

Why: a fine power map is hours of compute on one machine; its chunks are independent, so a
cluster of worker processes (one machine's cores, or many machines' through SLURM,
``docs/cluster.md``) runs one task per chunk. Each task builds its chunk's loadings from the
grid description (:class:`jaxdea.studies.loadings.Grid`: axes and drive pattern, a few kB; no
loadings or results travel to the worker), runs the chunk on one JAX device of its worker
process and writes the chunk's part into the store's ``.parts`` folder itself (a shared
filesystem); it returns only a small receipt (chunk, cell range, SHA-256, pid, seconds). The
client checks each part against its receipt (:meth:`jaxdea.studies.mapstore.Parts.load`) and
assembles the final store exactly as the single-process path does, so a map is the same
whichever path or worker count computed it (one device per chunk on both: a chunk sharded
over several devices rounds differently, ~1e-11 relative).

Fault tolerance comes from Dask (a task of a lost worker is rerun elsewhere) and from the
parts (a killed client leaves its finished parts; ``resume=True`` recomputes only the rest).
dask.distributed is imported only when a client is used.
"""

from __future__ import annotations

import os
import time
import uuid
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import SweepError
from ..engine.batch import (
    chain_heads,
    default_lanes,
    driven_membranes,
    run_cells,
    run_from_rest,
    take_cells,
)
from ..engine.coexist import coexisting
from ..engine.sharding import cell_sharded, use_cpu_cores
from ..engine.warmstart import neighbour_chain
from ..models.cone import Loading, Model
from .loadings import Grid
from .mapstore import Parts
from .sweep import VARIABLES, map_variables

#: Cluster chunk rule (paper and periodic): about this many chunks per worker, so that the
#: queue balances (a worker that gets slow chunks takes fewer) and a lost worker loses
#: little; chunks of at least :data:`MIN_CLUSTER_CHUNK` cells (a task costs ~10 ms of
#: scheduling and the lane pool needs cells to stay busy) and at most the single-process
#: chunk per device (:data:`jaxdea.studies.powermap.CHUNK_PER_DEVICE`).
CHUNKS_PER_WORKER = 4
MIN_CLUSTER_CHUNK = 256


def padded_cells(lo: int, size: int, n: int) -> np.ndarray:
    """The indices of the chunk of ``size`` cells from ``lo`` out of ``n``, past the last cell
    repeating it: every chunk of a batch has one shape (one compiled program); the caller
    drops the padding's results."""
    return np.minimum(np.arange(lo, lo + size), n - 1)


def run_chunk(model: Model, loadings: Loading, devices: tuple, *, protocol, successor, cycles,
              average, control, tol, early_exit, chain=None, real=None) -> dict[str, np.ndarray]:
    """One chunk's results; ``successor`` (continuation) is the pattern of one device's
    slice; ``chain`` (periodic, ``start="neighbour"``): ``(n_chain, rest)`` of the chunk's
    whole masses, of which the first ``real`` cells are the map's (the rest is padding)."""
    if chain is not None:  # warm starts along the map's second axis, whole masses per chunk
        n_chain, rest = chain
        blocks = -(-int(real) // (n_chain * rest))
        cells = np.arange(blocks * n_chain * rest)
        kw = dict(tol=tol, control=control, devices=devices,
                  driven=driven_membranes(loadings))
        mine, shape = take_cells(loadings, cells), (blocks, n_chain, rest)
        res, jac = neighbour_chain(model.actuator, mine, shape, with_jacobian=True, **kw)
        two, _ = coexisting(model.actuator, mine, shape, res, jacobian=jac, **kw)
        pad = np.minimum(np.arange(loadings.drive.frequency.shape[0]), cells.size - 1)
        out = {k: np.asarray(getattr(res, k)) for k in VARIABLES}
        out["coexist"] = two
        return {k: v[pad] for k, v in out.items()}
    if protocol == "continuation" and len(devices) > 1:  # whole chains per device slice
        res = cell_sharded(run_from_rest, devices)(
            model.actuator, loadings, jnp.asarray(np.tile(successor, len(devices)), jnp.int32),
            cycles=cycles, average=average, control=control,
            lanes=default_lanes(chain_heads(successor), devices), early_exit=early_exit,
            driven=driven_membranes(loadings))
    else:  # paper and periodic: dealt over the devices; continuation on one device
        res = run_cells(model, loadings, cycles=cycles, average=average, control=control,
                        protocol=protocol, successor=successor, tol=tol,
                        early_exit=early_exit, devices=devices)
    return {k: np.asarray(getattr(res, k)) for k in VARIABLES}


@dataclass
class ChunkJob:
    """What a worker needs to compute any chunk of one map: the model, the grid description,
    the chunk size, the protocol keywords of :func:`run_chunk` and the parts folder (None:
    the receipt carries the arrays instead)."""

    model: Model
    grid: Grid
    chunk: int
    n_cells: int
    run: dict[str, Any]
    parts: Parts | None

    def cells(self, i: int) -> tuple[int, int]:
        return i * self.chunk, min((i + 1) * self.chunk, self.n_cells)

    @property
    def variables(self) -> dict[str, tuple[str, str]]:
        """The per-cell variables of each chunk (:func:`~jaxdea.studies.sweep.map_variables`)."""
        return map_variables("neighbour" if self.run.get("chain") is not None else "rest")


def compute_part(job: ChunkJob, i: int) -> dict[str, Any]:
    """Task of one chunk on a worker: compute chunk ``i`` on one JAX device, write its part
    and return a receipt (chunk, cells, sha256, pid, seconds; ``arrays`` without a store).

    **Arguments:**

    - `job`: the map's :class:`ChunkJob`.
    - `i`: the chunk index.

    **Returns:**

    The receipt, a small dict.
    """
    use_cpu_cores(1)  # a fresh worker process: one device (no-op once JAX has started)
    t0 = time.perf_counter()
    lo, hi = job.cells(i)
    idx = padded_cells(lo, job.chunk, hi)
    out = run_chunk(job.model, job.grid.loadings(idx), tuple(jax.devices())[:1], real=hi - lo,
                    **job.run)
    got = {k: v[: hi - lo] for k, v in out.items()}
    receipt: dict[str, Any] = {"chunk": i, "cells": (lo, hi), "pid": os.getpid()}
    if job.parts is not None:
        receipt["sha256"] = job.parts.save(i, got, cells=(lo, hi))
    else:
        receipt["arrays"] = got
    receipt["seconds"] = time.perf_counter() - t0
    return receipt


#: Seconds :func:`check_client` waits for a worker when the cluster has none at the moment
#: (a nanny restarting a worker, a busy machine): once, on a 2-core CI machine running two
#: test processes and a 2-worker cluster, the scheduler listed none right after an
#: interrupted map, and the next map failed at once.
WORKER_WAIT = 30.0


def _workers(client) -> int:
    """The workers the scheduler lists now."""
    try:
        return len(client.scheduler_info(n_workers=-1)["workers"])
    except TypeError:  # older distributed: no n_workers argument
        return len(client.scheduler_info()["workers"])


def check_client(client, wait: float = WORKER_WAIT) -> int:
    """The number of workers of ``client`` (a ``dask.distributed.Client``); SweepError for
    anything else, or a client with no worker within ``wait`` seconds, before any compute.

    **Arguments:**

    - `client`: the Dask client.
    - `wait`: seconds to wait for a first worker where the cluster has none now.

    **Returns:**

    The number of workers.
    """
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise SweepError(f"client= needs dask.distributed ({exc}): pip install "
                         "'dask[distributed]'") from None
    if not isinstance(client, Client):
        raise SweepError(f"client must be a dask.distributed.Client, got "
                         f"{type(client).__name__}")
    try:
        n = _workers(client)
        if n < 1 and wait > 0:
            try:
                client.wait_for_workers(1, timeout=wait)
            except TimeoutError:
                pass
            n = _workers(client)
    except OSError as exc:
        raise SweepError(f"the Dask client cannot reach its scheduler: {exc}") from None
    if n < 1:
        raise SweepError(f"the Dask cluster has no worker (waited {wait:g} s): start workers "
                         "before running a map on it")
    return n


def cluster_units(n_units: int, unit: int, n_workers: int, max_cells: int) -> int:
    """Units (cells, or continuation chains) per chunk on a cluster of ``n_workers``:
    about :data:`CHUNKS_PER_WORKER` chunks per worker, each of at least
    :data:`MIN_CLUSTER_CHUNK` cells and at most ``max_cells``."""
    want = -(-n_units // (CHUNKS_PER_WORKER * n_workers))
    lo = max(1, -(-MIN_CLUSTER_CHUNK // unit))
    hi = max(1, max_cells // unit)
    return max(1, min(n_units, hi, max(lo, want)))


def queue_order(chunks, job: ChunkJob, n_f: int, n_rest: int) -> list[int]:
    """Chunks lowest frequency first (the lowest frequency index among a chunk's cells, then
    the chunk index), as :func:`jaxdea.engine.batch.schedule` queues cells."""
    def key(i: int) -> tuple[int, int]:
        lo, hi = job.cells(i)
        if hi - lo >= n_f * n_rest:
            return 0, i
        return int(((np.arange(lo, hi) // n_rest) % n_f).min()), i

    return sorted(chunks, key=key)


def run_on_cluster(client, job: ChunkJob, order: list[int], results: dict[str, np.ndarray],
                   on_done=None, max_tries: int = 3) -> int:
    """Run chunks ``order`` (submitted in that order, with decreasing priority) on
    ``client``'s workers, fill ``results`` from their parts (or receipts) and return the
    number of chunks computed. A part that fails its check is recomputed (at most
    ``max_tries`` times); a lost worker's task is rerun by Dask."""
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    tries = dict.fromkeys(order, 0)

    def submit(i: int, priority: int):
        tries[i] += 1
        return client.submit(compute_part, job, i, key=f"jaxdea-chunk-{i}-{token}-{tries[i]}",
                             priority=priority, pure=False)

    futures = [submit(i, len(order) - r) for r, i in enumerate(order)]
    done = 0
    queue = as_completed(futures)
    try:
        for fut in queue:
            receipt = fut.result()
            i = receipt["chunk"]
            lo, hi = job.cells(i)
            if job.parts is None:
                got = receipt["arrays"]
            else:
                got = job.parts.load(i, hi - lo, job.variables, cells=(lo, hi),
                                     sha256=receipt["sha256"])
            if got is None:
                if tries[i] >= max_tries:
                    raise SweepError(f"chunk {i}'s part failed its check {max_tries} times: "
                                     f"is another run writing to {job.parts.dir}?")
                fut = submit(i, len(order))
                futures.append(fut)
                queue.add(fut)
                continue
            for k in job.variables:
                results[k][lo:hi] = got[k]
            done += 1
            if on_done is not None:
                on_done()
    finally:
        client.cancel([f for f in futures if not f.done()])
    return done
