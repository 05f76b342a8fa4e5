"""Reduced DCDEA-LS power map with jaxdea vs scipy LSODA on sampled cells of it.

Map: 8 x 8 payloads (M 0.1-10 g, c 0.1-10 N s/m, log-spaced) x 64 frequencies spread over
1-200 Hz, membrane A driven, paper protocol (100 cycles from rest, mean of the last 5).
Baseline: the independent scipy transcription (tests/scipy_reference.py, LSODA rtol 1e-8)
on cells sampled at stratum centres of the map's frequency axis (random M, c), timed in the
same process. Prints trajectories/s for both, the ratio, peak memory (RSS) and the projected
time of the full 50 x 50 x 996 map on this machine.

The map runs on one JAX device per CPU core with the paper protocol's default early exit (a
cell stops once periodic to 1e-8, jaxdea.EARLY_EXIT); the LSODA cells (all 100 cycles)
check it. The projection interpolates the measured steps per cell over f onto the full map's
0.2 Hz grid and scales the measured time by the step count.

Periodic protocol: on a 1-200 Hz sweep of four payloads, the wall time of
``protocol="periodic"`` against ``protocol="paper"`` (every cell 100 cycles; and, for
information, with the early exit) on the same cells, and its largest P_out difference from a
400-cycle paper run over the cells where that run has converged (periodicity residual < 1e-8).

Diffrax baseline (issue 16): what a JAX user writes without jaxdea, a plain ``jax.vmap`` of
``diffrax.diffeqsolve`` (Tsit5, PID, the square-wave edges as ``jump_ts``, energies as states;
bench/diffrax_baseline.py) over ``4 x samples`` cells of the map (``4`` random payloads per
frequency stratum), against jaxdea's engine on the same cells in the same run
(``jaxdea.engine.batch.run_cells`` on every device, with the early exit, and without it:
equal work), both second calls; both are checked against LSODA on the first cell of each
stratum. ``diffrax_ratio`` = diffrax's wall time / jaxdea's (early exit on).

Full-map slice (issue 16): a real 1/10 slice of the paper-size map (all 50 x 50 payloads,
every 10th frequency of the 0.2 Hz grid: 250 000 cells), timed for the paper protocol and for
``periodic`` with warm starts across the grid, against LSODA and diffrax on sampled cells
(bench/full_map_slice.py, whose fields join this RESULT line: ``full_map_paper_s``,
``full_map_neighbour_s`` = slice wall time x 10, ``*_lsoda_ratio``, ``*_max_rel_err_vs_lsoda``,
``*_diffrax_ratio``, and the XLA compile inside each timed run). About 10 minutes on 2 cores;
``--no-slice`` skips it.

    python bench/powermap_bench.py [--quick] [--periodic-only] [--no-diffrax] [--no-slice]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import full_map_slice  # noqa: E402
import jaxdea  # noqa: E402
import scipy_reference  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 x 4 x 16, 10 cycles (smoke)")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--periodic-only", action="store_true", help="only the periodic section")
    ap.add_argument("--no-diffrax", action="store_true", help="skip the diffrax baseline")
    ap.add_argument("--no-slice", action="store_true",
                    help="skip the timed 1/10 slice of the full map (~10 min)")
    args = ap.parse_args()
    n_dev = jaxdea.use_cpu_cores(fuse_outputs=True)  # before any JAX work: as the CLI's map
    periodic = periodic_section(args.quick)
    if args.periodic_only:
        print("RESULT " + " ".join(f"{k}={v}" for k, v in periodic.items()))
        return
    n_pay, n_f, cycles = (4, 16, 10) if args.quick else (8, 64, 100)
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    mass = np.logspace(-4, -2, n_pay)
    damping = np.logspace(-1, 1, n_pay)
    freq = np.round(np.linspace(1.0, 200.0, n_f), 6)
    kw = dict(mass=mass, damping=damping, freq=freq, drive="A", cycles=cycles, average=5,
              progress=False)
    # warm-up on the same grid shape (so the same chunk shape: one compiled executable) with
    # other payload masses, so the timing below is run time only (a smaller warm-up grid
    # would compile a smaller chunk and leave the real compile inside the timed run)
    t0 = time.perf_counter()
    jaxdea.powermap(model, **{**kw, "mass": mass * 1.05})
    warm_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds = jaxdea.powermap(model, **kw)
    jax_s = time.perf_counter() - t0
    n_cells = ds.P_out.size
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ok = int((ds.status.values == 0).sum())
    print(f"jaxdea: {n_cells} cells x {cycles} cycles (early exit {jaxdea.EARLY_EXIT:g}: mean "
          f"{ds.cycles_run.values.mean():.1f} cycles run) on {n_dev} device(s) in {jax_s:.1f} s "
          f"({n_cells / jax_s:.1f} trajectories/s), warm-up (same shape) incl. compile "
          f"{warm_s:.1f} s, "
          f"status ok {ok}/{n_cells}, peak RSS {rss_mb:.0f} MB")

    rng = np.random.default_rng(0)
    idx_f = ((np.arange(args.samples) + 0.5) * n_f / args.samples).astype(int)
    times, errs = [], []
    for k in idx_f:
        i, j = rng.integers(n_pay), rng.integers(n_pay)
        t0 = time.perf_counter()
        ref = scipy_reference.reference_metrics("dcdea_ls", float(mass[i]), float(damping[j]),
                                                float(freq[k]), cycles=cycles, average=5,
                                                rtol=1e-8)
        times.append(time.perf_counter() - t0)
        cell = ds.isel(M=i, c=j, f=k)
        err = max(abs(float(cell.P_out) / ref["P_out"] - 1),
                  abs(float(cell.P_in) / ref["P_in"] - 1))
        errs.append(err)
        print(f"lsoda: M {mass[i] * 1e3:6.3f} g, c {damping[j]:6.3f} N s/m, f {freq[k]:6.1f} Hz: "
              f"{times[-1]:.2f} s, max rel err P_out/P_in {err:.1e}", flush=True)
    lsoda_tps = 1.0 / float(np.mean(times))
    jax_tps = n_cells / jax_s
    # cost follows solver steps; steps per cell vary smoothly with f for each payload (they
    # follow the simulated time cycles/f where cells run all cycles, and stop growing at low f
    # where cells exit early): interpolate log(steps) over f onto the paper's 0.2 Hz grid
    full_f = 1.0 + 0.2 * np.arange(996 if cycles == 100 else 100)
    steps = ds.steps.values.reshape(-1, n_f).astype(float)
    full_steps = np.array([np.exp(np.interp(full_f, freq, np.log(row))).sum() for row in steps])
    scale = 2500 * full_steps.mean() / steps.sum()
    full_h = jax_s * scale / 3600
    print(f"ratio (trajectories/s jaxdea / LSODA): {jax_tps / lsoda_tps:.0f}x; "
          f"projected full 50 x 50 x 996 map: {full_h:.1f} h here "
          f"(LSODA one core: {2500 * 996 / lsoda_tps / 86400:.0f} days)")
    dfx = {} if args.no_diffrax else diffrax_section(model, mass, damping, freq, idx_f,
                                                     cycles, rng)
    sliced = {}
    if not args.no_slice:  # last: the longest section (--quick: 5 x 5 payloads, every 50th f)
        sliced = full_map_slice.run_slice(["paper", "neighbour"], every=50 if args.quick else 10,
                                          samples=args.samples, quick=args.quick)
        own = {"lsoda_traj_per_s", "devices", "diffrax_s_per_cell"}
        sliced = {f"slice_{k}" if k in own else k: v for k, v in sliced.items()}
    print(f"RESULT jaxdea_traj_per_s={jax_tps:.2f} lsoda_traj_per_s={lsoda_tps:.3f} "
          f"ratio={jax_tps / lsoda_tps:.1f} cells={n_cells} cycles={cycles} jaxdea_s={jax_s:.1f} "
          f"peak_rss_mib={rss_mb:.0f} projected_full_map_s={full_h * 3600:.0f} "
          f"max_rel_err={max(errs):.2e} devices={n_dev} "
          f"mean_cycles_run={ds.cycles_run.values.mean():.1f} "
          + " ".join(f"{k}={v}" for k, v in {**dfx, **periodic, **sliced}.items()))


def diffrax_section(model, mass, damping, freq, idx_f, cycles, rng) -> dict[str, str]:
    """diffrax's vmapped ensemble vs jaxdea's engine on the same map cells (module doc)."""
    import jax

    from jaxdea.engine.batch import run_cells

    per = 4
    k = np.repeat(idx_f, per)
    m = mass[rng.integers(len(mass), size=k.size)]
    c = damping[rng.integers(len(damping), size=k.size)]
    f = freq[k]
    dfx = full_map_slice.diffrax_elsewhere(m, c, f, cycles=cycles)  # not under our flags
    loading = jaxdea.make_loadings(model, m, c, f, drive="A")
    devices = tuple(jax.devices())
    times = {}
    for name, ee in (("early_exit", jaxdea.EARLY_EXIT), ("all_cycles", None)):
        for _ in range(2):  # the second call is timed (compile excluded, as for diffrax)
            t0 = time.perf_counter()
            res = jax.block_until_ready(run_cells(model, loading, cycles=cycles, average=5,
                                                  early_exit=ee, devices=devices))
            times[name] = (time.perf_counter() - t0, res)
    errs = {"diffrax": [], "jaxdea": []}
    for i in range(0, k.size, per):
        ref = scipy_reference.reference_metrics("dcdea_ls", float(m[i]), float(c[i]),
                                                float(f[i]), cycles=cycles, average=5,
                                                rtol=1e-8)
        res = times["early_exit"][1]
        for name, po, pi in (("diffrax", dfx["P_out"][i], dfx["P_in"][i]),
                             ("jaxdea", float(res.P_out[i]), float(res.P_in[i]))):
            errs[name].append(max(abs(po / ref["P_out"] - 1), abs(pi / ref["P_in"] - 1)))
    jx, jx_all = times["early_exit"][0], times["all_cycles"][0]
    print(f"diffrax (plain vmap, Tsit5 PID, 1 device): {k.size} cells x {cycles} cycles in "
          f"{dfx['wall_s']:.2f} s (compile {dfx['compile_s']:.0f} s), all ok "
          f"{bool(dfx['ok'].all())}; jaxdea on the same cells ({len(devices)} device(s)): "
          f"{jx:.2f} s with its early exit, {jx_all:.2f} s all cycles; ratio "
          f"{dfx['wall_s'] / jx:.1f}x ({dfx['wall_s'] / jx_all:.1f}x equal work); max rel err "
          f"vs LSODA on {len(errs['jaxdea'])} cells: diffrax {max(errs['diffrax']):.1e}, "
          f"jaxdea {max(errs['jaxdea']):.1e}", flush=True)
    return {"diffrax_ratio": f"{dfx['wall_s'] / jx:.2f}",
            "diffrax_ratio_all_cycles": f"{dfx['wall_s'] / jx_all:.2f}",
            "diffrax_s": f"{dfx['wall_s']:.2f}", "diffrax_cells": str(k.size),
            "diffrax_err": f"{max(errs['diffrax']):.2e}",
            "diffrax_jaxdea_err": f"{max(errs['jaxdea']):.2e}"}


def periodic_section(quick: bool) -> dict[str, str]:
    """Periodic vs paper protocol on 1-200 Hz sweeps (same cells, same process)."""
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    n_f = 8 if quick else 32
    # one chunk with every cell; the warm-up runs other payloads on the same shape, so the
    # timed calls below reuse its compiled code
    kw = dict(mass=[2e-3, 1e-2], damping=[0.1, 1.0], freq=np.round(np.linspace(1, 200, n_f), 6),
              drive="A", progress=False)
    runs = {}
    for name, extra in (("paper", dict(protocol="paper", early_exit=None)),
                        ("paper_early_exit", dict(protocol="paper")),
                        ("periodic", dict(protocol="periodic"))):
        jaxdea.powermap(model, **{**kw, **extra, "mass": [5e-4, 5e-3], "damping": [0.3, 3.0]})
        t0 = time.perf_counter()
        runs[name] = (jaxdea.powermap(model, **{**kw, **extra}), time.perf_counter() - t0)
    long = jaxdea.powermap(model, **kw, cycles=400, early_exit=None)  # strict 400 cycles
    per, paper = runs["periodic"][0], runs["paper"][0]
    conv = (long.residual.values < 1e-8) & (long.status.values == 0)
    err = np.abs(per.P_out.values / long.P_out.values - 1)[conv]
    err100 = np.abs(paper.P_out.values / long.P_out.values - 1)[conv]
    speedup = runs["paper"][1] / runs["periodic"][1]
    vs_early = runs["paper_early_exit"][1] / runs["periodic"][1]
    n = per.P_out.size
    print(f"periodic: {n} cells over 1-200 Hz in {runs['periodic'][1]:.1f} s vs paper (100 "
          f"cycles) {runs['paper'][1]:.1f} s: {speedup:.1f}x; status ok "
          f"{int((per.status.values == 0).sum())}/{n}; mean cycles "
          f"{per.cycles_run.values.mean():.1f} (paper 100); max |P_out/P_out(400) - 1| over "
          f"the {int(conv.sum())} cells the 400-cycle run converged: {err.max():.1e} "
          f"(paper 100 cycles: {err100.max():.1e}); paper with early exit "
          f"{runs['paper_early_exit'][1]:.1f} s ({vs_early:.2f}x periodic's time)", flush=True)
    # (no full-map projection from these 128 cells: both timings are set by the critical
    # path of the 1 Hz cells, not by throughput; the speed-up compares like with like)
    return {"periodic_speedup": f"{speedup:.2f}", "periodic_max_rel_err": f"{err.max():.2e}",
            "periodic_s": f"{runs['periodic'][1]:.1f}", "paper100_s": f"{runs['paper'][1]:.1f}",
            "periodic_cells": str(n), "paper100_max_rel_err": f"{err100.max():.2e}",
            "paper_early_exit_s": f"{runs['paper_early_exit'][1]:.1f}",
            "periodic_speedup_vs_early_exit": f"{vs_early:.2f}"}


if __name__ == "__main__":
    main()
