"""Design study bench: cost of a P_max gradient over a P_max evaluation, and one optimisation.

1. SCDEA-LS, M = 2 g, c = 0.1 N s/m, band 20-160 Hz: P_max with ``jaxdea.peak_power``, and
   its gradient with respect to 10 parameters (``jax.value_and_grad``); each timed on its
   second call (the first compiles).
2. ``jaxdea.optimise``: 3 variables (spring stiffness, prestretch, disk mass), objective
   "pmax" over the same band, 8 starts, max_field 80 MV/m; wall time of the whole call
   (compile included) and the gain over the starting design.

    python bench/design_bench.py

Ends with one line: RESULT grad_over_eval=... optimise_s=... gain_pct=... starts=...
"""

from __future__ import annotations

import time
from pathlib import Path

import jax

import jaxdea

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["actuator.spring_stiffness", "actuator.deflection", "actuator.disk_mass",
         "membrane.prestretch", "membrane.thickness", "membrane.relative_permittivity",
         "membrane.dielectric.mu_A", "membrane.dielectric.tau", "voltage", "duty"]


def main() -> None:
    jaxdea.use_cpu_cores()
    model = jaxdea.load_config(ROOT / "configs" / "scdea_ls.toml")
    v = jaxdea.parameter_names(model)
    values = {k: v["actuator." + k if not k.startswith(("actuator", "voltage", "duty"))
                   else k] for k in NAMES}
    kw = dict(mass=2e-3, damping=0.1, band=(20.0, 160.0))
    pmax = lambda vals: jaxdea.peak_power(model, vals, **kw)["P_max"]  # noqa: E731
    vg = jax.value_and_grad(pmax)
    for _ in range(2):
        t0 = time.perf_counter()
        p = pmax(values)
        eval_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        p2, g = vg(values)
        grad_s = time.perf_counter() - t0
    print(f"P_max {float(p) * 1e3:.4f} mW: eval {eval_s:.2f} s, value+grad (10 params) "
          f"{grad_s:.2f} s", flush=True)
    vary = {"actuator.spring_stiffness": (100.0, 2000.0), "membrane.prestretch": (1.05, 1.6),
            "actuator.disk_mass": (1e-3, 5e-3)}
    t0 = time.perf_counter()
    res = jaxdea.optimise(model, vary, "pmax", starts=8, seed=0, **kw)
    opt_s = time.perf_counter() - t0
    gain = 100.0 * (res.objective / res.start_objective - 1.0)
    print(f"optimise: {res.values}, P_max {res.objective * 1e3:.4f} mW at "
          f"{res.f_at_P_max:.2f} Hz (start {res.start_objective * 1e3:.4f} mW), field "
          f"{res.field / 1e6:.2f} MV/m, active {res.active}, {len(res.history)} iterations")
    print(f"RESULT grad_over_eval={grad_s / eval_s:.2f} optimise_s={opt_s:.1f} "
          f"gain_pct={gain:.1f} starts=8")


if __name__ == "__main__":
    main()
