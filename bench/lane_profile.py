"""Profile of the lane engine's step: where a lane-step's time goes (issue 16, item 1).

Workload: DCDEA-LS, drive A (the headline map's configuration), 128 cells of a 16 x 8
payload grid (M 0.1-10 g, c 0.1-10 N s/m) at 60 Hz (one frequency: every lane busy until
the end, so the time per lane-step is not diluted by idle lanes), the paper protocol
without its early exit (every cell all its cycles: equal work in every variant),
one JAX device without XLA's Eigen pool (as each of a map's devices runs), one pool of
128 lanes.

Each variant runs in its own process (the engine's pieces are module globals that jit
captures at trace time) with one piece of the step replaced by a constant:

- ``full``: the engine as it is;
- ``no_returned``: no returned-energy integral (``driven=()``: P_in without recovery is then
  wrong, P_out untouched);
- ``no_hermite``: the amplitude from step ends only (no Hermite extrema);
- ``no_residual``: no periodicity residual at cycle ends;
- ``no_lockup``: no Gent margin;
- ``bare``: all four removed (the solver step, the controller and the queue only);
- ``single``: the full engine with single-precision lanes (``StepControl(precision="single")``).

For each: ns per lane-step (wall time / active lane-steps, best of 3), and the compiled
engine's size (HLO instructions and fusions of the whole optimised module). The difference
of a variant from ``full`` is what that piece costs.

    python bench/lane_profile.py [--cycles 20]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("full", "no_returned", "no_hermite", "no_residual", "no_lockup", "bare", "single")


def patch(variant: str) -> None:
    """Replace the variant's pieces in the engine's module globals (before any trace)."""
    import jax.numpy as jnp

    from jaxdea.engine import lanes
    from jaxdea.models.cone import ConeActuator

    parts = {"bare": ("hermite", "residual", "lockup"), "full": (), "single": ()}.get(
        variant, (variant[3:],))
    if "hermite" in parts:
        lanes.hermite_extrema = lambda x0, v0, x1, v1, h: (jnp.minimum(x0, x1),
                                                           jnp.maximum(x0, x1))
    if "residual" in parts:
        lanes.periodicity_residual = lambda y, prev: jnp.zeros_like(y.q[0])
    if "lockup" in parts:
        ConeActuator.lockup_margin = lambda self, y: jnp.ones_like(y.q[0])


def measure(variant: str, cycles: int, lanes: int = 128) -> dict:
    import jax
    import numpy as np

    import jaxdea
    from jaxdea.engine.lanes import run_protocol
    from jaxdea.studies.loadings import make_loadings

    jaxdea.use_cpu_cores(1)  # one device, no Eigen pool (as the map's devices run)
    patch(variant)
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    m, c = np.meshgrid(np.logspace(-4, -2, lanes // 8), np.logspace(-1, 1, 8), indexing="ij")
    f = np.full(m.size, 60.0)
    loads = make_loadings(model, m.ravel(), c.ravel(), f, "A")
    driven = () if variant in ("no_returned", "bare") else (0,)
    control = jaxdea.StepControl(precision="single" if variant == "single" else "double")
    run = jax.jit(lambda ld: run_protocol(model.actuator, ld, cycles=cycles, average=2,
                                          lanes=lanes, pools=(lanes,), driven=driven,
                                          control=control))
    hlo = run.lower(loads).compile().as_text()
    out = run(loads)
    jax.block_until_ready(out.P_out)
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        out = run(loads)
        jax.block_until_ready(out.P_out)
        best = min(best, time.perf_counter() - t0)
    steps = int(np.asarray(out.steps).sum())
    slots = lanes * int(np.asarray(out.steps).max())  # lane-steps incl. idle lanes at the end
    return dict(variant=variant, ns=1e9 * best / steps, busy=steps / slots, steps=steps,
                wall_s=best,
                hlo_instructions=len(re.findall(r"^\s+\S+ = ", hlo, re.M)),
                fusions=len(re.findall(r"^\s+\S+ = \S+ fusion\(", hlo, re.M)),
                P_out=float(np.asarray(out.P_out).mean()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20)
    ap.add_argument("--lanes", type=int, default=128, help="lanes = cells (a multiple of 8)")
    ap.add_argument("--variant", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.variant:
        print(json.dumps(measure(args.variant, args.cycles, args.lanes)))
        return
    rows = {}
    for v in VARIANTS:
        res = subprocess.run([sys.executable, __file__, "--variant", v, "--cycles",
                              str(args.cycles), "--lanes", str(args.lanes)],
                             capture_output=True, text=True, check=True)
        rows[v] = json.loads(res.stdout.strip().splitlines()[-1])
        r = rows[v]
        print(f"{v:12s} {r['ns']:7.1f} ns per lane-step  ({r['steps']} lane-steps in "
              f"{r['wall_s']:.2f} s, lanes {r['busy']:.0%} busy; HLO "
              f"{r['hlo_instructions']} instructions, "
              f"{r['fusions']} fusions; mean P_out {r['P_out']:.6e} W)", flush=True)
    full = rows["full"]["ns"]
    for v in VARIANTS[1:-1]:
        print(f"  {v[3:] if v != 'bare' else 'all four':10s} costs {full - rows[v]['ns']:6.1f} "
              f"ns ({(full - rows[v]['ns']) / full:5.1%} of a lane-step)")
    print("RESULT " + " ".join(f"{v}_ns={rows[v]['ns']:.1f}" for v in VARIANTS)
          + f" single_speedup={full / rows['single']['ns']:.2f}"
          f" full_hlo={rows['full']['hlo_instructions']} "
          f"full_fusions={rows['full']['fusions']} bare_over_full={rows['bare']['ns'] / full:.3f}")


if __name__ == "__main__":
    main()
