"""DE (paper 001 settings) vs L-BFGS vs Adam on one identification problem, in one process.

Prints, per method: model evaluations (a DE population counts as its size), wall time
(compilation included) and final loss, then one line
``RESULT de_evals=... de_loss=... de_s=... lbfgs_evals=... lbfgs_loss=... lbfgs_s=...
adam_evals=... adam_loss=... adam_s=...``.

Problem ``b`` (default): the SCDEA-LS membrane data of tests/test_calibrate.py. It has 3
payloads x 10 frequencies, P_out and amplitude, and 1 % noise. The fit is dielectric mu_A,
mu_B, tau from starts off by a factor of 3 (x3, /3, x3), inside boxes of a decade either side
of the truth. ``--with-jb`` also fits J_B, which the data do not identify: the loss is flat
along it to ~1e-4 relative, so DE, which samples the whole box, ends a hair lower (J_B at its
bound) than L-BFGS, which stops where the slope along J_B is below round-off. Problem
``a`` (the mass cone under the eq-25 multi-sine) is bench/calibration_mass_cone_bench.py,
which reuses :func:`compare_methods` below.

    python bench/calibration_bench.py                    # DE at paper settings (slow on CPU)
    python bench/calibration_bench.py --de-pop 40 --de-gens 20   # reduced
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))

from jaxdea.calibration import calibrate  # noqa: E402
from test_calibrate import FIT_B, PREDICT_B, make_problem_b  # noqa: E402

FIT = FIT_B[:3]  # mu_A, mu_B, tau: J_B (not identified) only with --with-jb
PREDICT = PREDICT_B


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="b", choices=["a", "b"])
    ap.add_argument("--de-pop", type=int, default=240, help="DE population (paper: 240)")
    ap.add_argument("--de-gens", type=int, default=115, help="DE generations (paper: 115)")
    ap.add_argument("--adam-steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--with-jb", action="store_true", help="also fit J_B (not identified)")
    args = ap.parse_args()
    if args.problem == "a":
        raise SystemExit("problem a (mass cone, eq-25 multi-sine): run "
                         "bench/calibration_mass_cone_bench.py")
    fit = FIT_B if args.with_jb else FIT
    start, data, truth, bounds = make_problem_b(fit=fit)
    common = dict(bounds=bounds, loss="relative", predict=PREDICT, curvature=False)
    runs = [
        ("de", dict(method="de", seed=args.seed, maxiter=args.de_gens,
                    de_options=dict(popsize=args.de_pop))),
        ("lbfgs", dict(method="lbfgs")),
        ("adam", dict(method="adam", maxiter=args.adam_steps, learning_rate=0.05)),
    ]
    compare_methods(start, data, fit, truth, common, runs)


def compare_methods(start, data, fit, truth, common: dict, runs, label: str = "") -> None:
    """Run ``calibrate`` once per ``(name, options)`` of ``runs`` (DE, L-BFGS, Adam), print
    evaluations, wall time, loss and parameter errors of each, the L-BFGS-vs-DE verdict and
    the ``RESULT`` line. ``label`` qualifies the DE run in the verdict (e.g. "reduced DE")."""
    out = {}
    for name, kw in runs:
        t0 = time.perf_counter()
        res = calibrate(start, data, fit, **common, **kw)
        wall = time.perf_counter() - t0
        err = {k.split(".")[-1]: f"{100 * (res.params[k] / truth[k] - 1):+.1f}%" for k in truth}
        print(f"{name:6s} evals {res.n_evals:7d}  wall {wall:8.1f} s  loss {res.loss:.4e}  "
              f"e_rms {res.e_rms:.3f} %  errors {err}", flush=True)
        out[name] = (res.n_evals, res.loss, wall)
    de, lb = out["de"], out["lbfgs"]
    rel = (lb[1] - de[1]) / de[1]
    verdict = "reaches" if rel <= 1e-6 else "does not reach"
    print(f"L-BFGS: {de[0] / lb[0]:.1f}x fewer model evaluations than DE"
          + (f" ({label})" if label else "") + f"; it {verdict} DE's final loss "
          f"({lb[1]:.8e} vs {de[1]:.8e}, relative difference {rel:+.1e}; 1e-6 counts as equal)")
    print("RESULT " + " ".join(f"{k}_evals={v[0]} {k}_loss={v[1]:.6e} {k}_s={v[2]:.1f}"
                               for k, v in out.items()))


if __name__ == "__main__":
    main()
