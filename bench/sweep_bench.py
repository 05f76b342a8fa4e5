"""Full paper sweep of DCDEA-LS with jaxdea vs scipy LSODA on sampled frequencies.

Paper 000 protocol: 996 frequencies 1-200 Hz (0.2 Hz step), 100 cycles from rest each,
mean of the last 5; M = 2 g, c = 0.1 N s/m, membrane A driven. jaxdea runs the whole sweep
as one jitted call (compile time reported apart). The baseline is the independent scipy
transcription (tests/scipy_reference.py, LSODA, rtol 1e-8 as in the shared performance
reference) on frequencies sampled at the centres of equal strata of the sweep, so their
mean estimates the mean LSODA cost per trajectory of the same sweep; cells solved by both
are also compared for accuracy.

    python bench/sweep_bench.py [--samples 8] [--rtol 1e-6] [--quick]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import jax  # noqa: E402

import jaxdea  # noqa: E402
import scipy_reference  # noqa: E402
from jaxdea.protocol import run_protocol  # noqa: E402
from jaxdea.sweep import default_lanes  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=8, help="LSODA trajectories")
    ap.add_argument("--rtol", type=float, default=1e-6, help="jaxdea tolerance")
    ap.add_argument("--lanes", type=int, default=None)
    ap.add_argument("--quick", action="store_true", help="10 cycles instead of 100 (smoke)")
    args = ap.parse_args()
    cycles = 10 if args.quick else 100
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    freq = np.round(1.0 + 0.2 * np.arange(996), 6)
    control = jaxdea.StepControl(rtol=args.rtol)
    loads = jaxdea.make_loadings(model, 2e-3, 0.1, freq, "A")
    lanes = args.lanes or default_lanes(freq.size)

    fn = jax.jit(functools.partial(run_protocol, cycles=cycles, average=5, control=control,
                                   lanes=lanes))
    t0 = time.perf_counter()
    compiled = fn.lower(model.actuator, loads).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = compiled(model.actuator, loads)
    jax.block_until_ready(res.P_out)
    jax_s = time.perf_counter() - t0
    steps = np.asarray(res.steps)
    p_out = np.asarray(res.P_out)
    print(f"jaxdea: {freq.size} trajectories x {cycles} cycles in {jax_s:.2f} s "
          f"(+ compile {compile_s:.2f} s), {jax_s / freq.size * 1e3:.2f} ms/trajectory, "
          f"{steps.sum():.3g} steps, {jax_s / steps.sum() * 1e9:.0f} ns/lane-step, "
          f"lanes {lanes}, status ok {int((np.asarray(res.status) == 0).sum())}/{freq.size}")
    i = int(np.argmax(p_out))
    print(f"jaxdea: P_max {p_out[i] * 1e3:.3f} mW at {freq[i]:g} Hz")

    idx = ((np.arange(args.samples) + 0.5) * freq.size / args.samples).astype(int)
    times, errs = [], []
    for k in idx:
        t0 = time.perf_counter()
        ref = scipy_reference.reference_metrics("dcdea_ls", 2e-3, 0.1, float(freq[k]),
                                                cycles=cycles, average=5, rtol=1e-8)
        times.append(time.perf_counter() - t0)
        err = max(abs(p_out[k] / ref["P_out"] - 1), abs(float(res.P_in[k]) / ref["P_in"] - 1))
        errs.append(err)
        print(f"lsoda: f = {freq[k]:6.1f} Hz  {times[-1]:6.2f} s   "
              f"P_out {ref['P_out'] * 1e3:8.4f} mW (jaxdea {p_out[k] * 1e3:8.4f})  "
              f"max rel err P_out/P_in {err:.1e}", flush=True)
    lsoda = float(np.mean(times))
    jax_per = jax_s / freq.size
    print(f"lsoda: mean {lsoda:.3f} s/trajectory over {len(idx)} stratified frequencies; "
          f"projected full sweep {lsoda * freq.size / 3600:.2f} h on one core")
    print(f"ratio (LSODA s/traj / jaxdea s/traj): {lsoda / jax_per:.0f}x")
    print(f"RESULT jaxdea_s_per_traj={jax_per:.5f} lsoda_s_per_traj={lsoda:.4f} "
          f"ratio={lsoda / jax_per:.1f} compile_s={compile_s:.2f} jaxdea_sweep_s={jax_s:.2f} "
          f"trajectories={freq.size} cycles={cycles} rtol={args.rtol} lanes={lanes} "
          f"max_rel_err={max(errs):.2e} lsoda_samples={len(idx)}")


if __name__ == "__main__":
    main()
