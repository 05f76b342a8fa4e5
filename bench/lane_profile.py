"""Profile of the lane engine's step: where a lane-step's time goes (issue 16, item 1).

Workload: DCDEA-LS, drive A (the headline map's configuration), 128 cells of a 16 x 8
payload grid (M 0.1-10 g, c 0.1-10 N s/m) at 60 Hz (one frequency: every lane busy until
the end, so the time per lane-step is not diluted by idle lanes), the paper protocol
without its early exit (every cell all its cycles: equal work in every variant),
one JAX device without XLA's Eigen pool (as each of a map's devices runs), one pool of
128 lanes.

Each variant has one piece of the step replaced by a constant (the engine's pieces are
module globals that jit captures at trace time, so each variant is traced and compiled
under its own patch, and the patch is undone before the next):

- ``full``: the engine as it is;
- ``no_returned``: no returned-energy integral (``driven=()``: P_in without recovery is then
  wrong, P_out untouched);
- ``no_hermite``: the amplitude from step ends only (no Hermite extrema);
- ``no_residual``: no periodicity residual at cycle ends;
- ``no_lockup``: no Gent margin;
- ``bare``: all four removed (the solver step, the controller and the queue only);
- ``single``: the full engine with single-precision lanes (``StepControl(precision="single")``).

All variants are compiled first and then timed in one process, interleaved round by round
(full, no_returned, ..., full, no_returned, ...): this machine's speed drifts by +-20 % from
one minute to the next, which swamped differences of 10 % when each variant ran in its own
process at its own time. For each: ns per lane-step (wall time / active lane-steps, best
of ``--rounds``, and the spread of the rounds), and the compiled engine's size (HLO
instructions and fusions of the whole optimised module). The difference of a variant from
``full`` is what that piece costs.

    python bench/lane_profile.py [--cycles 100] [--rounds 5]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import contextlib
import re
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("full", "no_returned", "no_hermite", "no_residual", "no_lockup", "bare", "single")


@contextlib.contextmanager
def patched(variant: str):
    """Replace the variant's pieces in the engine's module globals while tracing; undo after."""
    import jax.numpy as jnp

    from jaxdea.engine import lanes
    from jaxdea.models.cone import ConeActuator

    saved = (lanes.hermite_extrema, lanes.periodicity_residual, ConeActuator.lockup_margin)
    parts = {"bare": ("hermite", "residual", "lockup"), "full": (), "single": ()}.get(
        variant, (variant[3:],))
    if "hermite" in parts:
        lanes.hermite_extrema = lambda x0, v0, x1, v1, h: (jnp.minimum(x0, x1),
                                                           jnp.maximum(x0, x1))
    if "residual" in parts:
        lanes.periodicity_residual = lambda y, prev: jnp.zeros_like(y.q[0])
    if "lockup" in parts:
        ConeActuator.lockup_margin = lambda self, y: jnp.ones_like(y.q[0])
    try:
        yield
    finally:
        lanes.hermite_extrema, lanes.periodicity_residual, ConeActuator.lockup_margin = saved


def workload(lanes: int = 128):
    """The profile's model and cells: ``(config, loadings)``, ``lanes`` payloads at 60 Hz."""
    import numpy as np

    import jaxdea
    from jaxdea.studies.loadings import make_loadings

    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    m, c = np.meshgrid(np.logspace(-4, -2, lanes // 8), np.logspace(-1, 1, 8), indexing="ij")
    f = np.full(m.size, 60.0)
    return model, make_loadings(model, m.ravel(), c.ravel(), f, "A")


def compile_variant(variant: str, cycles: int, lanes: int = 128):
    """The variant's engine, compiled for the profile's cells: ``(run, loads, hlo_text)``."""
    import jax

    import jaxdea
    from jaxdea.engine.lanes import run_protocol

    model, loads = workload(lanes)
    driven = () if variant in ("no_returned", "bare") else (0,)
    control = jaxdea.StepControl(precision="single" if variant == "single" else "double")
    with patched(variant):
        run = jax.jit(lambda ld: run_protocol(model.actuator, ld, cycles=cycles, average=2,
                                              lanes=lanes, pools=(lanes,), driven=driven,
                                              control=control)).lower(loads).compile()
    return run, loads, run.as_text()


def timed(run, loads) -> tuple[float, object]:
    import jax

    t0 = time.perf_counter()
    out = run(loads)
    jax.block_until_ready(out.P_out)
    return time.perf_counter() - t0, out


def main() -> None:
    import numpy as np

    import jaxdea

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--lanes", type=int, default=128, help="lanes = cells (a multiple of 8)")
    args = ap.parse_args()
    jaxdea.use_cpu_cores(1)  # one device, no Eigen pool (as the map's devices run)
    progs = {v: compile_variant(v, args.cycles, args.lanes) for v in VARIANTS}
    walls = {v: [] for v in VARIANTS}
    outs = {}
    for v, (run, loads, _) in progs.items():  # one untimed run each (first-call costs)
        outs[v] = timed(run, loads)[1]
    for _ in range(args.rounds):
        for v, (run, loads, _) in progs.items():
            walls[v].append(timed(run, loads)[0])
    rows = {}
    for v, (_, _, hlo) in progs.items():
        steps = np.asarray(outs[v].steps)
        n = int(steps.sum())
        w = np.array(walls[v])
        rows[v] = dict(ns=1e9 * w.min() / n, spread=w.max() / w.min() - 1, steps=n,
                       busy=n / (args.lanes * int(steps.max())), wall_s=w.min(),
                       hlo_instructions=len(re.findall(r"^\s+\S+ = ", hlo, re.M)),
                       fusions=len(re.findall(r"^\s+\S+ = \S+ fusion\(", hlo, re.M)),
                       P_out=float(np.asarray(outs[v].P_out).mean()))
        r = rows[v]
        print(f"{v:12s} {r['ns']:7.1f} ns per lane-step (rounds within +{r['spread']:.0%}; "
              f"{r['steps']} lane-steps in {r['wall_s']:.2f} s, lanes {r['busy']:.0%} busy; "
              f"HLO {r['hlo_instructions']} instructions, {r['fusions']} fusions; "
              f"mean P_out {r['P_out']:.6e} W)", flush=True)
    full = rows["full"]["ns"]
    for v in VARIANTS[1:-1]:
        print(f"  {v[3:] if v != 'bare' else 'all four':10s} costs {full - rows[v]['ns']:6.1f} "
              f"ns ({(full - rows[v]['ns']) / full:5.1%} of a lane-step)")
    print("RESULT " + " ".join(f"{v}_ns={rows[v]['ns']:.1f}" for v in VARIANTS)
          + f" single_speedup={full / rows['single']['ns']:.2f}"
          f" full_hlo={rows['full']['hlo_instructions']} "
          f"full_fusions={rows['full']['fusions']} bare_over_full={rows['bare']['ns'] / full:.3f}"
          f" max_spread={max(r['spread'] for r in rows.values()):.3f}")


if __name__ == "__main__":
    main()
