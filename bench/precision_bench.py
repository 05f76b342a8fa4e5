"""Single- against double-precision lanes on the bench map (issue 16, item 3).

Map: powermap_bench's, DCDEA-LS drive A, 8 x 8 payloads (M 0.1-10 g, c 0.1-10 N s/m,
log-spaced) x 64 frequencies over 1-200 Hz, 100 cycles from rest, last 5 averaged. Four runs
in one process, each after a warm-up on the same grid shape (other masses), on one JAX
device per core:

- ``double``: float64 lanes, every cell all 100 cycles (the reference);
- ``single``: float32 lanes (``StepControl(precision="single")``), all 100 cycles: equal
  work, so its time ratio is what float32 buys per step;
- ``double_early_exit``: float64 with the default early exit (1e-8), what a user runs;
- ``single_early_exit``: float32 with the tightest early exit it can reach (1e-5,
  :data:`jaxdea.engine.precision.SINGLE_EARLY_EXIT_MIN`).

Prints, for each, the wall time and the largest and 99th-percentile relative differences of
P_out, P_in and the amplitude from ``double``, over the cells steady in both runs (where the
reference's last cycles are not periodic, its average is not a steady-state power). The
issue's target for ``single``: <= 1e-3 on P_out and P_in.

    python bench/precision_bench.py [--quick]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import jaxdea
from jaxdea.engine.precision import SINGLE_EARLY_EXIT_MIN

ROOT = Path(__file__).resolve().parents[1]
RUNS = {"double": ("double", None), "single": ("single", None),
        "double_early_exit": ("double", jaxdea.EARLY_EXIT),
        "single_early_exit": ("single", SINGLE_EARLY_EXIT_MIN)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 x 4 x 16, 20 cycles (smoke)")
    args = ap.parse_args()
    n_dev = jaxdea.use_cpu_cores()
    n_pay, n_f, cycles = (4, 16, 20) if args.quick else (8, 64, 100)
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    mass, damping = np.logspace(-4, -2, n_pay), np.logspace(-1, 1, n_pay)
    freq = np.round(np.linspace(1.0, 200.0, n_f), 6)
    kw = dict(damping=damping, freq=freq, drive="A", cycles=cycles, average=5, progress=False)
    out, secs = {}, {}
    for name, (precision, early_exit) in RUNS.items():
        run = dict(kw, control=jaxdea.StepControl(precision=precision), early_exit=early_exit)
        jaxdea.powermap(model, mass=mass * 1.05, **run)  # same shape: compile excluded
        t0 = time.perf_counter()
        out[name] = jaxdea.powermap(model, mass=mass, **run)
        secs[name] = time.perf_counter() - t0
    ref = out["double"]
    res = {"cells": str(ref.P_out.size), "devices": str(n_dev)}
    for name, ds in out.items():
        # over the cells that are steady in both runs: where the reference's last cycles are
        # not periodic, its 5-cycle average is not a steady-state power to compare with
        both = (ref.steady.values & ds.steady.values).ravel()
        errs = {k: np.abs(ds[k].values / ref[k].values - 1).ravel()[both]
                for k in ("P_out", "P_in", "amplitude")}
        worst = np.unravel_index(np.flatnonzero(both)[np.argmax(errs["P_in"])], ref.P_in.shape)
        ok = int((ds.status.values == 0).sum())
        print(f"{name:18s} {secs[name]:6.1f} s ({secs['double'] / secs[name]:4.2f}x double), "
              f"mean cycles {float(ds.cycles_run.mean()):5.1f}, status ok {ok}/{ds.P_out.size}; "
              f"vs double over the {both.sum()} cells steady in both: " + ", ".join(
                  f"{k} max {e.max():.1e} p99 {np.percentile(e, 99):.1e}"
                  for k, e in errs.items())
              + f" (P_in's worst at f = {freq[worst[2]]:g} Hz)", flush=True)
        res[f"{name}_s"] = f"{secs[name]:.1f}"
        if name != "double":
            res[f"{name}_speedup"] = f"{secs['double'] / secs[name]:.2f}"
            for k in ("P_out", "P_in"):
                res[f"{name}_{k}_err"] = f"{errs[k].max():.2e}"
    res["single_vs_double_early_exit"] = (
        f"{secs['double_early_exit'] / secs['single_early_exit']:.2f}")
    print("RESULT " + " ".join(f"{k}={v}" for k, v in res.items()))


if __name__ == "__main__":
    main()
