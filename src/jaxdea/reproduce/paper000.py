"""Paper 000's calibration: what is fitted, within which bounds, and the staged fit
(differential evolution for the basins, then L-BFGS from the best candidates), with jaxdea's
own optimisers on the claims loss (:mod:`.claims`, :class:`.objective.ClaimsObjective`).

Everything the paper states is kept (geometry, thickness, prestretch, permittivity,
electrode thickness and resistance, spring, deflection, voltage); the membrane's and the
electrode's Gent and Maxwell constants (one set shared by the three configurations) and the
disk mass are fitted. The bounds and their sources are in ``docs/paper000.md``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from ..calibration import DE, LBFGS, write_fitted_config
from ..config import load_config
from .claims import CLAIMS, HEAVY, LIGHT, claim_terms, quantities_of
from .objective import LOCAL, ClaimsObjective
from .peaks import PeakSearch, peak_table

__all__ = ["BOUNDS", "CONFIGS", "DESIGN_COLUMNS", "FIT", "FitPlan", "calibrate_paper000",
           "load_models", "margins", "write_configs", "write_design_table"]

#: The fitted parameters (paths shared by the three configurations).
FIT = ("membrane.dielectric.mu_A", "membrane.dielectric.J_A", "membrane.dielectric.mu_B",
       "membrane.dielectric.J_B", "membrane.dielectric.tau",
       "membrane.electrode.mu_A", "membrane.electrode.J_A", "membrane.electrode.mu_B",
       "membrane.electrode.J_B", "membrane.electrode.tau", "actuator.disk_mass")

#: Physically plausible bounds (SI) for ELASTOSIL Film 2030 and carbon-black silicone
#: electrodes (sources: docs/paper000.md).
BOUNDS = {
    "membrane.dielectric.mu_A": (0.15e6, 1.0e6), "membrane.dielectric.J_A": (5.0, 150.0),
    "membrane.dielectric.mu_B": (0.02e6, 1.0e6), "membrane.dielectric.J_B": (5.0, 150.0),
    "membrane.dielectric.tau": (1e-4, 5e-2),
    "membrane.electrode.mu_A": (0.3e6, 6.0e6), "membrane.electrode.J_A": (3.0, 100.0),
    "membrane.electrode.mu_B": (0.05e6, 3.0e6), "membrane.electrode.J_B": (3.0, 100.0),
    "membrane.electrode.tau": (1e-4, 5e-2),
    "actuator.disk_mass": (0.5e-3, 5.0e-3),
}

#: The three configurations and their reference configs (repo-relative).
CONFIGS = {"scdea_ls": "configs/scdea_ls.toml", "dcdea_rr": "configs/dcdea_rr.toml",
           "dcdea_ls": "configs/dcdea_ls.toml"}


def load_models(root: str | Path = ".", configs: dict | None = None) -> dict:
    """``{config name: Model}`` of the three configurations, from ``configs`` (default
    :data:`CONFIGS`, relative to ``root``)."""
    root = Path(root)
    return {k: load_config(root / v) for k, v in (configs or CONFIGS).items()}


@dataclasses.dataclass(frozen=True)
class FitPlan:
    """The stages of the calibration.

    **Arguments:**

    - `population`, `generations`: DE (paper 001: 240 x 115).
    - `de_search`: the peak search inside DE (coarse and fast).
    - `starts`: L-BFGS runs, from the best distinct DE candidates.
    - `lbfgs_iterations`: iterations of each.
    - `search`: the peak search of the L-BFGS stage and of the final check (100 cycles).
    - `seed`: DE's seed.
    """

    population: int = 32
    generations: int = 20
    de_search: PeakSearch = PeakSearch(band=(30.0, 200.0), coarse=5.0, cycles=60,
                                       early_exit=1e-6)
    starts: int = 2
    lbfgs_iterations: int = 8
    search: PeakSearch = PeakSearch(band=(30.0, 200.0), coarse=4.0)
    seed: int = 0


def _distinct(theta: np.ndarray, losses: np.ndarray, k: int, tol: float = 0.05) -> list[int]:
    """Indices of the ``k`` lowest losses whose log-parameters differ by more than ``tol``."""
    out: list[int] = []
    if k <= 0:
        return out
    for i in np.argsort(losses):
        if not np.isfinite(losses[i]):
            break
        if all(np.max(np.abs(np.log(theta[i] / theta[j]))) > tol for j in out):
            out.append(int(i))
        if len(out) == k:
            break
    return out


def calibrate_paper000(models: dict, plan: FitPlan = FitPlan(), *, log=None,
                       verbose: bool = True) -> dict:
    """Fit :data:`FIT` to the claims of paper 000.

    **Arguments:**

    - `models`: :func:`load_models` (the start values; every one inside :data:`BOUNDS`).
    - `plan`: :class:`FitPlan`.
    - `log`: an ``.npz`` path keeping every evaluated design (a rerun resumes DE from the
      best members found so far).
    - `verbose`: print progress.

    **Returns:**

    ``{"theta": best (n,), "loss": its loss, "names": FIT, "de": {...}, "lbfgs": [{...}],
    "evals": {"de": n, "lbfgs": n}, "wall_s": {"de": s, "lbfgs": s}, "objective": the
    ClaimsObjective}``.
    """
    obj = ClaimsObjective(models, FIT, BOUNDS, search=plan.de_search, log=log)
    n = len(FIT)
    lo = np.array([p.ulo for p in obj.params])
    hi = np.array([p.uhi for p in obj.params])
    rng = np.random.default_rng(plan.seed)
    init = lo + (hi - lo) * _latin(rng, plan.population, n)
    init[0] = np.array([float(p.u_of_theta(p.init)) for p in obj.params])  # the reference
    if obj.records["loss"]:  # resume: the best designs seen so far seed the population
        seen = np.log(np.array(obj.records["theta"]))
        best = np.argsort(np.array(obj.records["loss"]))[:plan.population // 2]
        init[1:1 + best.size] = seen[best]
    t0 = time.time()
    obj.stage = "de"
    n0 = len(obj.records["loss"])
    if plan.generations > 0:
        de = DE(population=plan.population, generations=plan.generations, init=init)
        sol = de.minimise(obj, seed=plan.seed, verbose=verbose)
        de_theta, de_message, de_history = sol.theta, sol.message, sol.progress.history
    else:  # DE done before (the log): its best design
        if not obj.records["loss"]:
            raise ValueError("generations = 0 needs a log with DE evaluations to start from")
        i = int(np.nanargmin(obj.records["loss"]))
        de_theta, de_message, de_history = np.array(obj.records["theta"][i]), "from log", []
    t_de, n_de = time.time() - t0, len(obj.records["loss"]) - n0
    theta_all = np.array(obj.records["theta"])
    loss_all = np.array(obj.records["loss"])
    de_mask = np.array(obj.records["stage"]) == "de"
    picks = _distinct(theta_all[de_mask], loss_all[de_mask], plan.starts)
    starts = theta_all[de_mask][picks]
    obj.search, obj.stage = plan.search, "lbfgs"
    runs = []
    t1, n1 = time.time(), len(obj.records["loss"])
    for s in starts:
        obj.params = [dataclasses.replace(p, init=float(v)) for p, v in zip(obj.params, s)]
        try:
            r = LBFGS(maxiter=plan.lbfgs_iterations, tol=1e-6).minimise(obj, jac="fwd",
                                                                        verbose=verbose)
            runs.append(dict(start=s, theta=r.theta, message=r.message,
                             history=r.progress.history))
        except Exception as exc:  # noqa: BLE001 - a failed start is reported, not fatal
            runs.append(dict(start=s, theta=s, message=f"failed: {exc}", history=[]))
    t_lb, n_lb = time.time() - t1, len(obj.records["loss"]) - n1
    # the final choice: every candidate checked with the same (100-cycle) peak search
    cands = np.stack([de_theta] + [r["theta"] for r in runs] + list(starts))
    obj.stage = "check"
    final = obj.losses(cands)
    best = int(np.nanargmin(final))
    return dict(theta=cands[best], loss=float(final[best]), names=FIT,
                de=dict(theta=de_theta, message=de_message, history=de_history),
                lbfgs=runs, candidates=cands, candidate_losses=final,
                evals=dict(de=n_de, lbfgs=n_lb, check=len(cands)),
                wall_s=dict(de=t_de, lbfgs=t_lb), objective=obj)


def _latin(rng, k: int, n: int) -> np.ndarray:
    """A Latin hypercube of ``k`` points in [0, 1]^n."""
    u = (rng.random((k, n)) + np.arange(k)[:, None]) / k
    for j in range(n):
        u[:, j] = u[rng.permutation(k), j]
    return u


def write_configs(theta, loss: float, out_dir, root: str | Path = ".") -> list[Path]:
    """``configs/paper000/<config>.toml``: the reference configs with the fitted values of
    :data:`FIT` replaced and tagged ``fitted`` with the loss they came from."""
    root, out_dir = Path(root), Path(out_dir)
    tag = f"fitted: paper000 claims loss {loss:.4g} (docs/paper000.md)"
    written = []
    for name, rel in CONFIGS.items():
        params = {"actuator." + k if not k.startswith("actuator.") else k: float(v)
                  for k, v in zip(FIT, theta)}
        path = write_fitted_config(
            root / rel, out_dir / Path(rel).name, params,
            header=f"Paper 000 ({name}): material constants and disk mass fitted to the "
                   "paper's claims\nby `python bench/paper000_calibration.py`; every other "
                   "value as in the reference config.")
        lines = []
        for line in path.read_text().splitlines():
            if line.rstrip().endswith("chosen (fitted)"):
                line = line.rstrip()[:-len("chosen (fitted)")] + tag
            elif line.rstrip().endswith(" (fitted)"):
                line = line.rstrip()[:-len(" (fitted)")].replace("chosen", tag)
            elif line.rstrip().endswith("# fitted"):
                line = line.rstrip()[:-len("fitted")] + tag
            elif line.startswith("[membrane.") and "chosen" in line:
                line = line.split("#")[0] + "# Table S.II is missing: fitted to paper 000's claims"
            lines.append(line)
        path.write_text("\n".join(lines) + "\n")
        written.append(path)
    return written


#: The columns of ``configs/paper000/calibration_designs.csv`` (one row per evaluated design).
DESIGN_COLUMNS = ("stage", "loss", "margin_1a", "margin_2a", "fig9_error", *FIT)


def margins(qs: dict) -> dict[str, np.ndarray]:
    """The conflict coordinates of designs: finding 1a's margin ``log(P_RR / P_LS-B)`` and
    finding 2a's ``log(P_RR-anti / max(P_LS-anti, P_LS-in))`` at c = 0.1 (positive: met),
    and the Fig 9 error: the largest of its four parts' errors (the two maxima and their
    frequencies) in units of their tolerances (at most 1: met)."""
    def p(case, kind="P"):
        return np.asarray(qs[f"{kind}:{case}:{LIGHT:g}"], float)

    fig9 = [c for c in CLAIMS if c.name in ("fig9-global", "fig9-local")]
    err = np.max(np.abs(np.stack([np.asarray(e, float) for c in fig9
                                  for e in claim_terms(c, qs)])), axis=0)
    return dict(
        margin_1a=np.log(p("DCDEA-RR") / p("DCDEA-LS-B")),
        margin_2a=np.log(p("DCDEA-RR-anti") / np.maximum(p("DCDEA-LS-anti"),
                                                         p("DCDEA-LS-in"))),
        fig9_error=err)


def write_design_table(obj, path) -> Path:
    """Every design ``obj`` (a :class:`ClaimsObjective`) evaluated, as a CSV of
    :data:`DESIGN_COLUMNS`: the multi-start evidence and the trade-off plot's data."""
    path = Path(path)
    qs = {k: np.asarray(v, float) for k, v in obj.quantities.items()}
    m = margins(qs)
    theta = np.asarray(obj.records["theta"], float)
    with open(path, "w") as fh:
        fh.write(",".join(DESIGN_COLUMNS) + "\n")
        for i, loss in enumerate(obj.records["loss"]):
            vals = [obj.records["stage"][i], f"{loss:.6g}"] + \
                [f"{m[k][i]:.6g}" for k in ("margin_1a", "margin_2a", "fig9_error")] + \
                [f"{v:.6g}" for v in theta[i]]
            fh.write(",".join(vals) + "\n")
    return path


def claims_check(models: dict, theta, search: PeakSearch = PeakSearch()) -> dict:
    """The quantities of the claims for designs ``theta`` (K, n) by ``search``."""
    table = peak_table(models, FIT, np.atleast_2d(theta), mass=2e-3, dampings=(LIGHT, HEAVY),
                       search=search, local=LOCAL)
    return dict(table=table, quantities=quantities_of(table), claims=CLAIMS)
