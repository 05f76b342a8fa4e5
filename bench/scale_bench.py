"""Scaling of a power map over Dask workers on this machine: 1 vs 2 worker processes.

The same DCDEA-LS map (paper protocol, 100 cycles with the default early exit, membrane A)
runs on ``LocalCluster(n_workers=W, processes=True, threads_per_worker=1)`` for W = 1 and 2,
with the same chunk size, so both runs do identical work (and give identical numbers, checked).
Every worker compiles the chunk program before the clock starts (a one-chunk map run on each
worker with ``client.run``), so the times are compute plus scheduling, not compilation.
Task overhead: the mean round trip of a trivial task (submit, run, result) on the 2-worker
cluster, sequentially. Per run it also prints each worker's summed task compute time (Dask's
task stream): their sum against wall x workers separates contention for the cores (the sum
grows with 2 workers) from idle workers (load imbalance, overhead).

    python bench/scale_bench.py [--quick]

Ends with one line: RESULT speedup_2_workers=... task_overhead_ms=... cells=...
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

import jaxdea

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "dcdea_ls.toml"


def _noop(x):
    return x


def _warm(mass, damping, freq, chunk):
    """Compile the chunk program in this worker process (one map of one chunk)."""
    jaxdea.use_cpu_cores(1)
    model = jaxdea.load_config(CONFIG)
    jaxdea.powermap(model, mass=mass, damping=damping, freq=freq, chunk_cells=chunk,
                    progress=False)
    return os.getpid()


def run(n_workers: int, grid: dict, chunk: int):
    from distributed import Client, LocalCluster, get_task_stream

    model = jaxdea.load_config(CONFIG)
    t0 = time.perf_counter()
    with LocalCluster(n_workers=n_workers, processes=True, threads_per_worker=1,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        client.wait_for_workers(n_workers, timeout=120)
        start = time.perf_counter() - t0
        t0 = time.perf_counter()
        warm = dict(mass=grid["mass"][:1], damping=grid["damping"][:1],
                    freq=np.linspace(grid["freq"][0], grid["freq"][-1], chunk), chunk=chunk)
        client.run(_warm, **warm)
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        with get_task_stream(client) as stream:
            ds = jaxdea.powermap(model, **grid, chunk_cells=chunk, progress=False,
                                 client=client)
        wall = time.perf_counter() - t0
        busy: dict = {}
        for task in stream.data:
            for ss in task["startstops"]:
                if ss["action"] == "compute":
                    busy[task["worker"]] = busy.get(task["worker"], 0) + ss["stop"] - ss["start"]
        print(f"  task compute s per worker: {sorted(round(b, 2) for b in busy.values())}, "
              f"sum {sum(busy.values()):.2f} s (wall x workers {wall * n_workers:.2f} s)",
              flush=True)
        overhead = None
        if n_workers > 1:
            client.submit(_noop, -1, pure=False).result()
            t0 = time.perf_counter()
            n = 100
            for i in range(n):
                client.submit(_noop, i, pure=False).result()
            overhead = (time.perf_counter() - t0) / n
    print(f"{n_workers} worker(s): cluster start {start:.1f} s, compile {compile_s:.1f} s, "
          f"map {wall:.2f} s, {ds['P_out'].size / wall:.0f} cells/s, "
          f"{ds.attrs['chunks_computed']} chunks", flush=True)
    return ds, wall, overhead


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a small map (smoke)")
    args = ap.parse_args()
    n_m, n_c, n_f = (2, 2, 40) if args.quick else (4, 4, 240)
    grid = dict(mass=np.geomspace(1e-3, 5e-3, n_m), damping=np.geomspace(0.05, 0.5, n_c),
                freq=np.linspace(20.0, 200.0, n_f))
    cells = n_m * n_c * n_f
    chunk = cells // 16  # 16 equal chunks: 16 tasks on 1 worker, 8 each on 2
    print(f"map {n_m} x {n_c} x {n_f} = {cells} cells, {chunk}-cell chunks, "
          f"{os.cpu_count()} CPU(s)", flush=True)
    one, t1, _ = run(1, grid, chunk)
    two, t2, overhead = run(2, grid, chunk)
    same = all(np.array_equal(one[k].values, two[k].values, equal_nan=True)
               for k in one.data_vars)
    print(f"maps identical: {same}")
    print(f"RESULT speedup_2_workers={t1 / t2:.2f} task_overhead_ms={1e3 * overhead:.1f} "
          f"cells={cells}")


if __name__ == "__main__":
    main()
