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
``a`` (the mass cone under the eq-25 multi-sine) is not available yet (see docs/models.md
section 8).

    python bench/calibration_bench.py                    # DE at paper settings (slow on CPU)
    python bench/calibration_bench.py --de-pop 40 --de-gens 20   # reduced
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import equinox as eqx
import numpy as np

import jaxdea
from jaxdea.caldata import FrequencyResponse
from jaxdea.calibrate import calibrate, frequency_response, get_params, set_params

CONFIG = Path(__file__).parents[1] / "configs" / "scdea_ls.toml"
FIT = ["dielectric.mu_A", "dielectric.mu_B", "dielectric.tau"]
PREDICT = functools.partial(frequency_response, cycles=12, average=4)


def problem_b(seed: int = 1, fit=FIT):
    true = jaxdea.load_config(CONFIG)
    f1 = np.linspace(30.0, 150.0, 10)
    f = np.tile(f1, 3)
    mass = np.repeat([1e-3, 4e-3, 16e-3], f1.size)
    shape = FrequencyResponse(f=f, mass=mass, damping=0.1, P_out=np.ones_like(f))
    clean = eqx.filter_jit(lambda m: PREDICT(m, shape))(true)
    rng = np.random.default_rng(seed)
    noisy = {k: np.asarray(v) * (1 + 0.01 * rng.standard_normal(f.size))
             for k, v in clean.items()}
    data = FrequencyResponse(f=f, mass=mass, damping=0.1, **noisy)
    truth = get_params(true, fit)
    start = set_params(true, {k: v * (3.0 if i % 2 == 0 else 1 / 3)
                              for i, (k, v) in enumerate(truth.items())})
    bounds = {k: (v / 10, v * 10) for k, v in truth.items()}
    return start, data, truth, bounds


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
        raise SystemExit("problem a (mass cone, eq-25 multi-sine) is not available yet: "
                         "see docs/models.md section 8")
    fit = FIT + ["dielectric.J_B"] if args.with_jb else FIT
    start, data, truth, bounds = problem_b(fit=fit)
    common = dict(bounds=bounds, loss="relative", predict=PREDICT, curvature=False)
    out = {}
    runs = [
        ("de", dict(method="de", seed=args.seed, maxiter=args.de_gens,
                    de_options=dict(popsize=args.de_pop))),
        ("lbfgs", dict(method="lbfgs")),
        ("adam", dict(method="adam", maxiter=args.adam_steps, learning_rate=0.05)),
    ]
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
    print(f"L-BFGS: {de[0] / lb[0]:.0f}x fewer model evaluations than DE; it {verdict} DE's "
          f"final loss ({lb[1]:.8e} vs {de[1]:.8e}, relative difference {rel:+.1e}; "
          "1e-6 counts as equal)")
    print("RESULT " + " ".join(f"{k}_evals={v[0]} {k}_loss={v[1]:.6e} {k}_s={v[2]:.1f}"
                               for k, v in out.items()))


if __name__ == "__main__":
    main()
