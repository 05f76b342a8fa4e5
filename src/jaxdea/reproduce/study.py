"""``jaxdea reproduce paper000``: the study of paper 000 regenerated from the fitted set —
Figs 6, 7, 9, 10 and 11 as PNGs, ``claims.md`` and ``claims.csv`` (every number a claim rests
on, by the paper's 100-cycle protocol), the power maps behind the figures, and, where not
every claim is met, the trade-off between the claims that conflict.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from .._checks import SweepError
from ..params import get_params
from ..studies.powermap import powermap
from ..studies.sweep import sweep
from . import figures
from .claims import CLAIMS, HEAVY, LIGHT, MASS, derive, met, q, quantities_of
from .objective import LOCAL
from .paper000 import CONFIGS, FIT, load_models, margins
from .peaks import CASES, PeakSearch, peak_table

__all__ = ["SIZES", "Size", "claim_rows", "reproduce_paper000"]

CSV_COLUMNS = ("claim", "case", "M_kg", "c_Ns_per_m", "f_Hz", "P_out_W", "met")


@dataclasses.dataclass(frozen=True)
class Size:
    """The grids of a reproduction: the maps' payload masses (kg), dampings (N s/m) and
    frequencies (Hz), and the claims' peak search."""

    masses: tuple
    dampings: tuple
    freq: tuple
    search: PeakSearch
    cycles: int = 100


SIZES = {
    "full": Size(masses=(1e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2),
                 dampings=tuple(float(c) for c in np.geomspace(0.1, 10.0, 9)),
                 freq=tuple(np.arange(20.0, 200.1, 2.0)),
                 search=PeakSearch(band=(30.0, 200.0), coarse=4.0)),
    # small: 2 x 2 x 2 = 8 cells per map, the size a one-cell sweep is padded to
    # (engine.batch.batch_cells), so the maps run the claims' confirming sweeps' programs
    "small": Size(masses=(1e-4, 2e-3), dampings=(0.1, 10.0), freq=(60.0, 140.0),
                  search=PeakSearch(band=(40.0, 180.0), coarse=35.0, fine=5.0, half=1,
                                    cycles=20, average=2),
                  cycles=20),
}


def _theta(models: dict) -> np.ndarray:
    return np.array(list(get_params(models["dcdea_ls"], list(FIT)).values()), float)


def _confirm(models: dict, qs: dict, size: Size) -> tuple[dict, list[str]]:
    """Every peak of ``qs`` (design 0) run again at its frequency by the paper protocol:
    P, L, eta and R from those cells (the numbers of claims.csv), and the cells whose last
    cycles were not periodic (the paper protocol's number there is not a steady state)."""
    out = {k: np.asarray(v)[:1].copy() for k, v in qs.items()}
    unsteady: list[str] = []
    for case, spec in CASES.items():
        for c in (LIGHT, HEAVY):
            for kind, fkind in (("P", "f"), ("L", "fL")):
                fk = q(fkind, case, c)
                if fk not in qs or not math.isfinite(float(qs[fk][0])):
                    continue
                f = round(float(qs[fk][0]), 2)
                ds = sweep(models[spec.config], mass=MASS, damping=c, freq=[f],
                           drive=spec.drive, phase=spec.phase or 0.0, cycles=size.cycles,
                           average=min(5, size.cycles))
                p = float(ds["P_out"].values[0]) if int(ds["status"].values[0]) == 0 \
                    else math.nan
                out[q(kind, case, c)] = np.array([p])
                if not bool(ds["steady"].values[0]):
                    unsteady.append(f"{case} c={c:g} f={f:g} Hz")
                out[fk] = np.array([f])
                if kind == "P":
                    out[q("Pin", case, c)] = np.array([float(ds["P_in"].values[0])])
    derive(out)
    return out, unsteady


def _cell(key: str, qs: dict):
    """``(case, c, f, P)`` of a P-like quantity (P, L) of design 0."""
    kind, case, c = key.split(":")
    f = qs[("fL" if kind == "L" else "f") + f":{case}:{c}"]
    return case, float(c), float(np.asarray(f)[0]), float(np.asarray(qs[key])[0])


def claim_rows(qs: dict, claims=CLAIMS) -> list[dict]:
    """claims.csv's rows: one per P_out a claim rests on (design 0 of ``qs``)."""
    rows = []
    for claim in claims:
        ok = "yes" if met(claim, qs) else "no"
        keys: list[str] = []
        for part in claim.parts:
            for u in part.uses:
                kind, case, c = u.split(":")
                if kind in ("P", "L"):
                    keys.append(u)
                elif kind in ("eta", "f"):
                    keys.append(f"P:{case}:{c}")
                elif kind == "fL":
                    keys.append(f"L:{case}:{c}")
                elif kind == "R":
                    keys += [f"P:{case}:{c}", f"P:DCDEA-RR:{c}"]
        for k in dict.fromkeys(keys):
            case, c, f, p = _cell(k, qs)
            rows.append(dict(claim=claim.name, case=case, M_kg=MASS, c_Ns_per_m=c,
                             f_Hz=round(f, 2), P_out_W=f"{p:.6g}", met=ok))
    return rows


def _fmt(key: str, v: float) -> str:
    kind, case, c = key.split(":")
    unit = {"P": ("mW", 1e3), "L": ("mW", 1e3), "f": ("Hz", 1.0), "fL": ("Hz", 1.0),
            "eta": ("%", 100.0), "R": ("x", 1.0)}[kind]
    label = {"P": "P_max", "L": "local max", "f": "f*", "fL": "f local", "eta": "eff",
             "R": "ratio"}[kind]
    return f"{case} c={c}: {label} {v * unit[1]:.3g} {unit[0]}"


def _describe(claim, qs) -> str:
    keys = dict.fromkeys(u for part in claim.parts for u in part.uses)
    return "; ".join(_fmt(k, float(np.asarray(qs[k])[0])) for k in keys)


def _claims_md(fitted: dict, reference: dict, path: Path, note: str) -> None:
    lines = ["# Paper 000: claims against the fitted and the reference parameter sets", "",
             note, "",
             "| claim | paper | fitted set | reference set | met? |", "|---|---|---|---|---|"]
    for claim in CLAIMS:
        lines.append(f"| {claim.name} ({claim.where}) | {claim.text} | "
                     f"{_describe(claim, fitted)} | {_describe(claim, reference)} | "
                     f"{'yes' if met(claim, fitted) else 'no'} |")
    n = sum(met(c, fitted) for c in CLAIMS)
    nr = sum(met(c, reference) for c in CLAIMS)
    lines += ["", f"Met: {n} of {len(CLAIMS)} with the fitted set, {nr} of {len(CLAIMS)} "
                  "with the reference set."]
    path.write_text("\n".join(lines) + "\n")


def _conflicts(fitted: dict) -> list[str]:
    return [c.name for c in CLAIMS if not met(c, fitted)]


def _tradeoff(out: Path, log: Path, fitted: dict) -> Path | None:
    """The conflicting claims over every design the calibration evaluated
    (``configs/paper000/calibration_designs.csv``): finding 1a's and 2a's margins against
    the Fig 9 error, the fitted set marked."""
    if not log.exists():
        return None
    data = np.genfromtxt(log, delimiter=",", names=True, dtype=None, encoding="utf-8")
    if data.size == 0 or "margin_2a" not in data.dtype.names:
        return None
    m = {k: float(v[0]) for k, v in margins(fitted).items()}
    return figures.tradeoff(data, m, out / "tradeoff.png")


def reproduce_paper000(out, *, configs=None, reference=None, size: str = "full",
                       root: str | Path = ".", progress: bool = True) -> dict:
    """Regenerate paper 000's study from a parameter set.

    **Arguments:**

    - `out`: the output folder (made if missing; files in it are replaced).
    - `configs`: ``{config name: path}`` of the fitted set (default
      ``configs/paper000/<name>.toml``); `reference`: the reference set (default
      :data:`jaxdea.reproduce.paper000.CONFIGS`).
    - `size`: ``"full"`` or ``"small"`` (:data:`SIZES`; small is for tests).
    - `root`: the repository root the default paths are relative to.
    - `progress`: progress bars on the maps.

    **Returns:**

    ``{"claims": {name: met}, "files": [paths], "wall_s": s}``.
    """
    if size not in SIZES:
        raise SweepError(f"size = {size!r} must be one of {', '.join(SIZES)}")
    t0 = time.time()
    root, out = Path(root), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sz = SIZES[size]
    configs = configs or {k: f"configs/paper000/{k}.toml" for k in CONFIGS}
    fitted_models = load_models(root, configs)
    ref_models = load_models(root, reference or CONFIGS)
    theta = np.stack([_theta(fitted_models), _theta(ref_models)])
    table = peak_table(fitted_models, list(FIT), theta, mass=MASS, dampings=(LIGHT, HEAVY),
                       search=sz.search, local=LOCAL)
    qs = quantities_of(table)
    fitted, unsteady = _confirm(fitted_models, {k: np.asarray(v)[:1] for k, v in qs.items()},
                                sz)
    reference_q, _ = _confirm(ref_models, {k: np.asarray(v)[1:] for k, v in qs.items()}, sz)
    files = []
    rows = claim_rows(fitted)
    with open(out / "claims.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    files.append(out / "claims.csv")
    note = (f"Every number by the paper's protocol ({sz.cycles} cycles from rest, the last "
            f"{min(5, sz.cycles)} averaged) at the peak frequency found by the peak search "
            f"(M = {MASS * 1e3:g} g; size {size!r}).")
    if unsteady:
        note += (" Not steady after those cycles (the fitted set's number is the paper "
                 "protocol's, not a periodic orbit's): " + "; ".join(unsteady) + ".")
    _claims_md(fitted, reference_q, out / "claims.md", note)
    files.append(out / "claims.md")
    maps = {}
    for case, spec in CASES.items():
        maps[case] = powermap(fitted_models[spec.config], mass=list(sz.masses),
                              damping=list(sz.dampings), freq=list(sz.freq), drive=spec.drive,
                              phase=None if spec.phase is None else [spec.phase],
                              cycles=sz.cycles, average=min(5, sz.cycles), progress=progress)
        if "phase" in maps[case].dims:
            maps[case] = maps[case].isel(phase=0, drop=True)
        maps[case].to_netcdf(out / f"map_{case}.nc")
        files.append(out / f"map_{case}.nc")
    files += [figures.fig6(maps, out / "fig6.png"), figures.fig7(maps, out / "fig7.png"),
              figures.fig9(maps, out / "fig9.png"), figures.fig10(maps, out / "fig10.png"),
              figures.fig11(maps, out / "fig11.png")]
    conflicts = _conflicts(fitted)
    if conflicts:
        t = _tradeoff(out, (root / configs["dcdea_ls"]).parent / "calibration_designs.csv",
                      fitted)
        if t is not None:
            files.append(t)
    return dict(claims={c.name: met(c, fitted) for c in CLAIMS}, files=files,
                wall_s=time.time() - t0, conflicts=conflicts)
