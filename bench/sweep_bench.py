"""Full paper sweep of DCDEA-LS with jaxdea vs scipy LSODA on sampled frequencies.

Paper 000 protocol: 996 frequencies 1-200 Hz (0.2 Hz step), 100 cycles from rest each,
mean of the last 5; M = 2 g, c = 0.1 N s/m, membrane A driven. jaxdea runs the whole sweep
as one jitted call over one JAX device per CPU core (compile time reported apart), with its
default early exit (a cell stops once periodic to 1e-8; jaxdea.EARLY_EXIT) and, for
comparison, strictly (every cell all 100 cycles). The baseline is the independent scipy
transcription (tests/scipy_reference.py, LSODA, rtol 1e-8 as in the shared performance
reference) on frequencies sampled at the centres of equal strata of the sweep, so their
mean estimates the mean LSODA cost per trajectory of the same sweep; cells solved by both
are also compared for accuracy.

    python bench/sweep_bench.py [--samples 8] [--rtol 1e-6] [--quick]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


import jaxdea  # noqa: E402
import scipy_reference  # noqa: E402


def timed_sweep(model, **kw):
    """(Dataset, first-call seconds incl. compile, second-call seconds = run time)."""
    t0 = time.perf_counter()
    jaxdea.sweep(model, **kw)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds = jaxdea.sweep(model, **kw)
    return ds, first, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=8, help="LSODA trajectories")
    ap.add_argument("--rtol", type=float, default=1e-6, help="jaxdea tolerance")
    ap.add_argument("--lanes", type=int, default=None)
    ap.add_argument("--quick", action="store_true", help="10 cycles instead of 100 (smoke)")
    args = ap.parse_args()
    n_dev = jaxdea.use_cpu_cores()  # before any JAX work: one device per core
    cycles = 10 if args.quick else 100
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    freq = np.round(1.0 + 0.2 * np.arange(996), 6)
    kw = dict(mass=2e-3, damping=0.1, freq=freq, drive="A", cycles=cycles, average=5,
              control=jaxdea.StepControl(rtol=args.rtol), lanes=args.lanes)

    runs = {}
    for name, early in (("default", jaxdea.EARLY_EXIT), ("strict", None)):
        ds, first, run_s = timed_sweep(model, **kw, early_exit=early)
        runs[name] = (ds, run_s, first - run_s)
        steps = ds.steps.values
        print(f"jaxdea {name} (early_exit={early}): {freq.size} trajectories in {run_s:.2f} s "
              f"(+ compile ~{first - run_s:.1f} s: first call minus second), "
              f"{run_s / freq.size * 1e3:.2f} ms/trajectory, {steps.sum():.3g} steps, "
              f"mean cycles {ds.cycles_run.values.mean():.1f}, {n_dev} device(s), status ok "
              f"{int((ds.status.values == 0).sum())}/{freq.size}", flush=True)
    ds, jax_s, compile_s = runs["default"]
    strict, strict_s, _ = runs["strict"]
    p_out = ds.P_out.values
    dev = np.abs(p_out / strict.P_out.values - 1)
    i = int(np.argmax(p_out))
    print(f"jaxdea: P_max {p_out[i] * 1e3:.3f} mW at {freq[i]:g} Hz; early exit vs strict: "
          f"max |P_out/P_out(strict) - 1| = {dev.max():.1e}")

    idx = ((np.arange(args.samples) + 0.5) * freq.size / args.samples).astype(int)
    times, errs = [], []
    for k in idx:
        t0 = time.perf_counter()
        ref = scipy_reference.reference_metrics("dcdea_ls", 2e-3, 0.1, float(freq[k]),
                                                cycles=cycles, average=5, rtol=1e-8)
        times.append(time.perf_counter() - t0)
        err = max(abs(p_out[k] / ref["P_out"] - 1), abs(float(ds.P_in[k]) / ref["P_in"] - 1))
        errs.append(err)
        print(f"lsoda: f = {freq[k]:6.1f} Hz  {times[-1]:6.2f} s   "
              f"P_out {ref['P_out'] * 1e3:8.4f} mW (jaxdea {p_out[k] * 1e3:8.4f})  "
              f"max rel err P_out/P_in {err:.1e}", flush=True)
    lsoda = float(np.mean(times))
    jax_per = jax_s / freq.size
    strict_per = strict_s / freq.size
    print(f"lsoda: mean {lsoda:.3f} s/trajectory over {len(idx)} stratified frequencies; "
          f"projected full sweep {lsoda * freq.size / 3600:.2f} h on one core")
    print(f"ratio (LSODA s/traj / jaxdea s/traj): {lsoda / jax_per:.0f}x "
          f"(strict, every cell 100 cycles: {lsoda / strict_per:.0f}x)")
    print(f"RESULT jaxdea_s_per_traj={jax_per:.5f} lsoda_s_per_traj={lsoda:.4f} "
          f"ratio={lsoda / jax_per:.1f} compile_s={compile_s:.2f} jaxdea_sweep_s={jax_s:.2f} "
          f"strict_s_per_traj={strict_per:.5f} strict_ratio={lsoda / strict_per:.1f} "
          f"early_exit_max_rel_dev={dev.max():.1e} devices={n_dev} "
          f"trajectories={freq.size} cycles={cycles} rtol={args.rtol} "
          f"max_rel_err={max(errs):.2e} lsoda_samples={len(idx)}")


if __name__ == "__main__":
    main()
