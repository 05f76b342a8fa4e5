"""A real 1/10 slice of paper 000's full power map, timed: the headline job measured, not projected.

The full map is DCDEA-LS, drive A, 50 x 50 payloads (M 0.1-10 g, c 0.1-10 N s/m, log-spaced)
x 996 frequencies (1-200 Hz every 0.2 Hz), 100 cycles from rest, last 5 averaged. This slice
keeps every payload and every 10th frequency (1, 3, ..., 199 Hz: 100 frequencies, 250 000
cells), so that its wall time x 10 is the full map's on this machine (the slice samples the
frequency axis evenly, and a cell's cost depends on its frequency and payload only).

Each protocol runs through ``jaxdea.powermap`` as a user would (one JAX device per core,
chunked, a store on disk that a killed run resumes from), after a warm-up on a small grid
(the shared pieces compile there; the slice's own chunk shape compiles inside the timed run,
as it would for a user: a few seconds of several minutes). The baseline, timed in the same
run, is the independent scipy transcription (tests/scipy_reference.py, LSODA rtol 1e-8,
every cell all 100 cycles) on cells sampled at stratum centres of the frequency axis (random
payloads); it also checks the map's P_out and P_in there, and at one cell of the lowest
frequency (not timed: a 1 Hz cell costs LSODA ~15x the mean cell).

    python bench/full_map_slice.py [--every 10] [--protocols paper,periodic,neighbour] [--quick]
        [--store DIR]   # keep the stores there (default: a temporary folder, removed)

``neighbour`` is the periodic protocol with warm starts across the grid
(``start="neighbour"``, :mod:`jaxdea.engine.warmstart`).
``paper`` runs with the default step policy, whose transient's extrapolation is on at this
size (``StepControl(extrapolate="auto")``, :mod:`jaxdea.engine.extrapolate`);
``paper_nojump`` is the same protocol without it (``StepControl(extrapolate=None)``, the
default before 2026-12-06), compared with ``paper`` cell by cell when both run.

Ends with one line: RESULT key=value ... (``full_map_<protocol>_s`` = slice wall time x
``every``, as the issue defines it; ``<protocol>_compile_s`` = XLA's compile time inside the
timed run, which that product counts ``every`` times where a real full map compiles once:
``full_map_<protocol>_compile_once_s`` = (wall - compile) x every + compile;
``<protocol>_diffrax_ratio`` = a plain vmapped ``diffrax.diffeqsolve``'s wall time
per sampled cell, ``bench/diffrax_baseline.py``, over the protocol's wall time per cell of the
slice; ``<protocol>_ns_per_cell_step`` = the timed run's wall time less its compile over all its
cells' steps; ``neighbour_coexist_cells`` = the warm-started map's cells with a second stable
orbit (``coexist``); ``platform`` = the devices' kind: on an accelerator the engine's lane pools are
as wide as a chunk, :func:`jaxdea.engine.batch.default_lanes`).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import jaxdea  # noqa: E402
import scipy_reference  # noqa: E402

#: The slice's protocols: powermap keywords.
PROTOCOLS = {"paper": dict(protocol="paper"), "periodic": dict(protocol="periodic"),
             "neighbour": dict(protocol="periodic", start="neighbour"),
             "paper_nojump": dict(protocol="paper",
                                  control=jaxdea.StepControl(extrapolate=None))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=10, help="keep every Nth frequency (1: full)")
    ap.add_argument("--protocols", default="paper,periodic,neighbour",
                    help="comma-separated: paper (100 cycles, early exit), periodic (from "
                         "rest), neighbour (periodic, warm starts across the grid), "
                         "paper_nojump (paper, StepControl(extrapolate=None))")
    ap.add_argument("--samples", type=int, default=8, help="LSODA cells")
    ap.add_argument("--quick", action="store_true", help="5 x 5 payloads (smoke)")
    ap.add_argument("--store", help="folder for the map stores (kept; default: temporary)")
    args = ap.parse_args()
    protocols = [p.strip() for p in args.protocols.split(",") if p.strip()]
    if any(p not in PROTOCOLS for p in protocols) or not protocols:
        sys.exit(f"--protocols must name some of {', '.join(PROTOCOLS)}, got "
                 f"{args.protocols!r}")
    if args.every < 1:
        sys.exit(f"--every must be >= 1, got {args.every}")
    jaxdea.use_cpu_cores(fuse_outputs=True)  # as the CLI's powermap
    out = run_slice(protocols, every=args.every, samples=args.samples, quick=args.quick,
                    store=args.store)
    print("RESULT " + " ".join(f"{k}={v}" for k, v in out.items()))


class CompileClock:
    """Seconds XLA spends compiling while :meth:`running` (JAX's backend-compile events):
    the slice's own chunk shape compiles inside its timed run, once, as it would for a user
    of the full map, so ``wall x every`` counts that compile ``every`` times."""

    def __init__(self):
        self.total, self._on = 0.0, False
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, name: str, secs: float, **_) -> None:
        if self._on and name == "/jax/core/compile/backend_compile_duration":
            self.total += secs

    def running(self, on: bool) -> None:
        self._on = on
        if on:
            self.total = 0.0


def run_slice(protocols: list[str], *, every: int = 10, samples: int = 8, quick: bool = False,
              store: str | None = None) -> dict[str, str]:
    """Time the slice under each of ``protocols`` (keys of :data:`PROTOCOLS`) and check it
    against LSODA and diffrax on ``samples`` cells; returns the RESULT fields (strings).
    Call :func:`jaxdea.use_cpu_cores` first."""
    n_dev = len(jax.devices())
    n_pay = 5 if quick else 50
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    mass, damping = np.logspace(-4, -2, n_pay), np.logspace(-1, 1, n_pay)
    full_f = np.round(1.0 + 0.2 * np.arange(996), 6)
    freq = full_f[::every]
    folder = Path(store) if store else Path(tempfile.mkdtemp(prefix="jaxdea-slice-"))
    folder.mkdir(parents=True, exist_ok=True)
    out: dict[str, str] = {"slice_cells": str(n_pay * n_pay * freq.size), "every": str(every),
                           "devices": str(n_dev), "platform": jax.devices()[0].platform}
    clock = CompileClock()
    maps, walls = {}, {}
    try:
        for protocol in protocols:
            kw = dict(mass=mass, damping=damping, freq=freq, drive="A", **PROTOCOLS[protocol])
            # warm-up on a small grid (its chunk shape differs: the slice's compiles in the
            # timed run, a few seconds, as it would for a user)
            t0 = time.perf_counter()
            jaxdea.powermap(model, **{**kw, "mass": mass[:2] * 1.05, "damping": damping[:2],
                                      "freq": freq[:min(freq.size, 8)]}, progress=False)
            warm = time.perf_counter() - t0
            path = folder / f"slice_{protocol}.zarr"
            clock.running(True)
            t0 = time.perf_counter()
            ds = jaxdea.powermap(model, **kw, store=path, resume=path.exists())
            wall = time.perf_counter() - t0
            clock.running(False)
            maps[protocol], walls[protocol] = ds, wall
            ok = int(((ds.status == 0) & ds.steady).sum())
            reused = ds.attrs["chunks_reused"]
            print(f"{protocol}: {ds.P_out.size} cells in {wall:.1f} s on {n_dev} device(s) "
                  f"({ds.P_out.size / wall:.0f} cells/s, its compile included; small "
                  f"warm-up {warm:.1f} s; "
                  f"{reused} chunk(s) reused from an interrupted run), steady with status 0: "
                  f"{ok}/{ds.P_out.size}, mean cycles {ds.cycles_run.values.mean():.1f}; full "
                  f"map x{every}: {wall * every / 60:.1f} min; XLA compile in the timed "
                  f"run {clock.total:.1f} s (a full map compiles once: "
                  f"{((wall - clock.total) * every + clock.total) / 60:.1f} min)", flush=True)
            out[f"full_map_{protocol}_s"] = f"{wall * every:.0f}"
            out[f"{protocol}_compile_s"] = f"{clock.total:.1f}"
            out[f"full_map_{protocol}_compile_once_s"] = (
                f"{(wall - clock.total) * every + clock.total:.0f}")
            out[f"slice_{protocol}_s"] = f"{wall:.1f}"
            steps = float(ds.steps.sum())  # every cell's steps, its chord periods included
            out[f"{protocol}_ns_per_cell_step"] = f"{(wall - clock.total) / steps * 1e9:.0f}"
            out[f"{protocol}_steady_ok"] = str(ok)
            if "coexist" in ds:  # warm starts: cells where a second stable orbit was found
                out[f"{protocol}_coexist_cells"] = str(int(ds.coexist.sum()))
            if reused:
                out[f"{protocol}_chunks_reused"] = str(reused)
        out.update(lsoda_check(maps, walls, mass, damping, freq, samples))
        out.update(diffrax_check(maps, walls, mass, damping, freq, samples))
        for pa, pb in (("paper", "periodic"), ("paper", "neighbour"), ("periodic", "neighbour"),
                       ("paper_nojump", "paper")):
            if pa not in maps or pb not in maps:
                continue
            a, b = maps[pa], maps[pb]
            both = ((a.status == 0) & a.steady & (b.status == 0) & b.steady).values
            diff = np.abs(b.P_out.values / a.P_out.values - 1)[both]
            print(f"{pb} vs {pa} P_out over {int(both.sum())} cells steady in both: max "
                  f"rel diff {diff.max():.1e}, median {np.median(diff):.1e}, above 1e-3: "
                  f"{int((diff > 1e-3).sum())}")
            out[f"{pb}_vs_{pa}_max_rel"] = f"{diff.max():.2e}"
            out[f"{pb}_vs_{pa}_above_1e-3"] = str(int((diff > 1e-3).sum()))
    finally:
        if not store:
            shutil.rmtree(folder, ignore_errors=True)
    return out


def _sampled(mass, damping, freq, samples):
    """The sampled cells' indices (M, c, f): stratum centres of f, random payloads (seed 0)."""
    rng = np.random.default_rng(0)
    idx_f = ((np.arange(samples) + 0.5) * freq.size / samples).astype(int)
    return [(int(rng.integers(mass.size)), int(rng.integers(damping.size)), int(k))
            for k in idx_f]


def diffrax_check(maps, walls, mass, damping, freq, samples) -> dict[str, str]:
    """What a JAX user writes without jaxdea (``bench/diffrax_baseline.py``: a plain vmap of
    ``diffrax.diffeqsolve``, Tsit5, PID, the edges as ``jump_ts``, 100 cycles from rest, mean
    of the last 5) on the sampled cells: its wall time per cell (second call, one device)
    against each protocol's wall time per cell of the slice, and its error against the map."""
    cells = _sampled(mass, damping, freq, samples)
    i, j, k = (np.array(a) for a in zip(*cells))
    m, c, f = mass[i], damping[j], freq[k]
    dfx = diffrax_elsewhere(m, c, f)
    per_cell = dfx["wall_s"] / len(cells)
    print(f"diffrax (plain vmap, 1 device): {len(cells)} sampled cells in {dfx['wall_s']:.2f} s "
          f"(second call; compile {dfx['compile_s']:.1f} s), {per_cell * 1e3:.1f} ms per cell; "
          f"all ok: {bool(dfx['ok'].all())}", flush=True)
    out = {"diffrax_s_per_cell": f"{per_cell:.4f}"}
    for p, ds in maps.items():
        mine = walls[p] / float(ds.P_out.size)
        errs = [abs(float(ds.P_out.isel(M=i, c=j, f=k)) / dfx["P_out"][n] - 1)
                for n, (i, j, k) in enumerate(cells)]
        out[f"{p}_diffrax_ratio"] = f"{per_cell / mine:.0f}"
        out[f"{p}_vs_diffrax_max_rel"] = f"{max(errs):.2e}"
    return out


#: The baseline in a process of its own, with the engine's CPU flags but without multi-output
#: fusion: XLA aborts compiling diffrax's saving under vmap with it (``jaxdea.engine.sharding.
#: MULTI_OUTPUT_FUSION``), which this bench's maps use as the CLI's do.
_DIFFRAX_CHILD = """
import json, sys
import numpy as np
sys.path.insert(0, {bench!r})
import jaxdea
jaxdea.use_cpu_cores()
import diffrax_baseline
model = jaxdea.load_config({config!r})
cells = json.loads(sys.stdin.read())
out = diffrax_baseline.diffrax_cells(model, *(np.array(cells[k]) for k in ("m", "c", "f")),
                                     cycles=cells["cycles"], average=5)
print(json.dumps({{k: np.asarray(v).tolist() for k, v in out.items()}}))
"""


def diffrax_elsewhere(m, c, f, cycles: int = 100) -> dict:
    """``diffrax_baseline.diffrax_cells`` of the DCDEA-LS cells ``(m, c, f)`` (``cycles``,
    the last 5 averaged), run in a child process without multi-output fusion."""
    import json
    import os
    import subprocess

    from jaxdea.engine.sharding import MULTI_OUTPUT_FUSION, without_extra_option

    env = dict(os.environ)
    env["XLA_FLAGS"] = without_extra_option(env.get("XLA_FLAGS", ""), MULTI_OUTPUT_FUSION)
    code = _DIFFRAX_CHILD.format(bench=str(Path(__file__).parent),
                                 config=str(ROOT / "configs" / "dcdea_ls.toml"))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         input=json.dumps({"m": list(map(float, m)), "c": list(map(float, c)),
                                           "f": list(map(float, f)), "cycles": int(cycles)}),
                         check=False)
    if res.returncode != 0:
        raise RuntimeError(f"the diffrax baseline failed:\n{res.stderr[-2000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    return {k: np.asarray(v) for k, v in out.items()}


def lsoda_check(maps, walls, mass, damping, freq, samples) -> dict[str, str]:
    """LSODA on sampled cells: its trajectories/s, the maps' errors there and the ratio of
    LSODA's time for the slice (one core) to each protocol's wall time."""
    times, errs = [], {p: [] for p in maps}
    # plus the lowest frequency (a random payload): the map's hardest cells for P_in, whose
    # time is left out of LSODA's mean (they are not a fair sample of the map's cost)
    low = (int(np.random.default_rng(1).integers(mass.size)),
           int(np.random.default_rng(2).integers(damping.size)), 0)
    for i, j, k in _sampled(mass, damping, freq, samples) + [low]:
        t0 = time.perf_counter()
        ref = scipy_reference.reference_metrics("dcdea_ls", float(mass[i]), float(damping[j]),
                                                float(freq[k]), cycles=100, average=5,
                                                rtol=1e-8)
        if (i, j, k) != low:
            times.append(time.perf_counter() - t0)
        for p, ds in maps.items():
            cell = ds.isel(M=i, c=j, f=k)
            if int(cell.status) == 0 and bool(cell.steady):
                errs[p].append(max(abs(float(cell.P_out) / ref["P_out"] - 1),
                                   abs(float(cell.P_in) / ref["P_in"] - 1)))
        print(f"lsoda: M {mass[i] * 1e3:.3g} g, c {damping[j]:.3g} N s/m, f {freq[k]:g} Hz: "
              f"{times[-1]:.2f} s; " + ", ".join(
                  f"{p} err {errs[p][-1]:.1e}" for p in maps if errs[p]), flush=True)
    lsoda_tps = 1.0 / float(np.mean(times))
    out = {"lsoda_traj_per_s": f"{lsoda_tps:.3f}"}
    for p, ds in maps.items():
        lsoda_s = float(ds.P_out.size) / lsoda_tps  # LSODA's time for the slice, one core
        out[f"{p}_max_rel_err_vs_lsoda"] = f"{max(errs[p]):.2e}" if errs[p] else "nan"
        out[f"{p}_lsoda_ratio"] = f"{lsoda_s / walls[p]:.0f}"
    return out


if __name__ == "__main__":
    main()
