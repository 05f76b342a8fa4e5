"""DE vs L-BFGS vs Adam on issue 5's problem (a), in one process: the mass cone of paper 002
(``jaxdea.huang2020()``) under an eq-25 multi-sine, synthetic data (1 % noise), six
spring/dashpot parameters (mu[0], tau[0], mu[2], tau[2], mu[3], tau[3]) from starts off by a
factor of 3, boxes of a decade either side of the truth. The problem is the one of
tests/test_calibrate_mass_cone.py (time-scaled drive: paper amplitudes, frequencies x5, one
2.28-s period, 115 samples, 228 fixed Kvaerno5 steps).

Prints, per method: model evaluations (a DE population counts as its size), wall time
(compilation included) and final loss, then one line
``RESULT de_evals=... de_loss=... de_s=... lbfgs_evals=... lbfgs_loss=... lbfgs_s=...
adam_evals=... adam_loss=... adam_s=...``.

DE at paper 001 settings (population 240, 115 generations, F 0.6, CR 0.9) is 27,600 model
evaluations, too slow for a CPU run here, so the default is a reduced DE (population 24,
12 generations); ``--paper`` runs the full settings. Gradients are reverse mode (diffrax's
adjoint cannot be forward-differentiated). A persistent compilation cache in a temporary
folder lets Adam reuse L-BFGS's compiled value-and-gradient (same HLO).

    python bench/calibration_mass_cone_bench.py            # reduced DE
    python bench/calibration_mass_cone_bench.py --paper    # DE at paper settings (slow)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).parent))

from calibration_bench import compare_methods  # noqa: E402
from jaxdea.calibration import DE_PAPER  # noqa: E402
from test_calibrate_mass_cone import FIT, problem_a  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paper", action="store_true", help="DE at paper 001 settings")
    ap.add_argument("--de-pop", type=int, default=24)
    ap.add_argument("--de-gens", type=int, default=12)
    ap.add_argument("--adam-steps", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    pop, gens = (DE_PAPER["popsize"], DE_PAPER["maxiter"]) if args.paper else (args.de_pop,
                                                                              args.de_gens)
    print(f"DE: {'paper settings' if args.paper else 'REDUCED budget'}: population {pop}, "
          f"{gens} generations, F {DE_PAPER['mutation']}, CR {DE_PAPER['recombination']}",
          flush=True)
    cache = tempfile.mkdtemp(prefix="jaxdea_bench_cache_")
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)

    start, data, truth, bounds, predict, _ = problem_a()
    common = dict(bounds=bounds, predict=predict, jac="rev", curvature=False)
    runs = [
        ("de", dict(method="de", seed=args.seed, maxiter=gens, de_options=dict(popsize=pop))),
        ("lbfgs", dict(method="lbfgs")),  # default tol 1e-10: tol 1e-8 stops 3 % above DE
        ("adam", dict(method="adam", maxiter=args.adam_steps, learning_rate=0.05)),
    ]
    compare_methods(start, data, FIT, truth, common, runs,
                    label="paper DE" if args.paper else "reduced DE")


if __name__ == "__main__":
    main()
