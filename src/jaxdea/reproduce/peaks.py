"""P_max of many designs at once: every drive case of paper 000 over a frequency band, by the
paper protocol in the lane engine, for a batch of parameter vectors (a DE population).

The peak of each (design, case, damping) is found in two batched stages: a coarse frequency
grid over the band, then a fine grid around the coarse maximum (or around the maximum inside
a sub-band, for a local peak such as Fig 9's near 70 Hz), and a parabola through the best fine
cell and its neighbours. Every stage of a case is one compiled call over designs x cells,
split over the host's devices by design with no collective (:func:`cell_sharded`).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..engine.batch import driven_membranes
from ..engine.lanes import run_protocol
from ..engine.protocols import EARLY_EXIT
from ..engine.sensitivity import stack_designs
from ..engine.sharding import cell_sharded
from ..engine.step_control import StepControl
from ..models.cone import Model
from ..studies.builder import make_builder, resolve, split_names
from ..studies.distributed import padded_cells

__all__ = ["CASES", "Case", "PeakSearch", "case_builder", "peak_table"]


@dataclasses.dataclass(frozen=True)
class Case:
    """A drive case of paper 000: the configuration (``"scdea_ls"``, ``"dcdea_rr"``,
    ``"dcdea_ls"``), the driven membranes (``"A"``, ``"B"``, ``"both"``) and B's phase lag."""

    config: str
    drive: str = "A"
    phase: float | None = None


#: The seven cases of paper 000 by the names of its claims (Figs 6-11).
CASES: dict[str, Case] = {
    "SCDEA-LS": Case("scdea_ls"),
    "DCDEA-RR": Case("dcdea_rr"),
    "DCDEA-LS-A": Case("dcdea_ls", "A"),
    "DCDEA-LS-B": Case("dcdea_ls", "B"),
    "DCDEA-RR-anti": Case("dcdea_rr", "both", math.pi),
    "DCDEA-LS-anti": Case("dcdea_ls", "both", math.pi),
    "DCDEA-LS-in": Case("dcdea_ls", "both", 0.0),
}


@dataclasses.dataclass(frozen=True)
class PeakSearch:
    """How :func:`peak_table` finds P_max.

    **Arguments:**

    - `band`: ``(f_lo, f_hi)``, Hz, of the coarse grid.
    - `coarse`: coarse grid spacing, Hz.
    - `fine`: fine grid spacing, Hz; `half`: fine cells either side of the coarse maximum.
    - `cycles`, `average`, `early_exit`: the paper protocol (100 cycles, the last 5
      averaged; a cell periodic to ``early_exit`` stops early).
    - `control`: the lane engine's step policy.
    - `lanes`: lane pool per design.
    """

    band: tuple[float, float] = (20.0, 200.0)
    coarse: float = 4.0
    fine: float = 1.0
    half: int = 4
    cycles: int = 100
    average: int = 5
    early_exit: float | None = EARLY_EXIT
    control: StepControl = StepControl()
    lanes: int = 32

    def coarse_grid(self) -> np.ndarray:
        lo, hi = self.band
        return np.linspace(lo, hi, int(round((hi - lo) / self.coarse)) + 1)


def case_builder(model: Model, names, case: Case, mass: float, freq, damping):
    """The :class:`~jaxdea.studies.builder.Builder` of ``case`` over cells with frequencies
    ``freq`` and dampings ``damping`` (equal-length 1-d arrays), varying ``names``."""
    _, full, pay = split_names(resolve(model, list(names)))
    build = make_builder(model, full, pay, mass=mass, damping=0.0, freq=np.asarray(freq),
                         drive=case.drive, phase=case.phase, shift=False)
    return eqx.tree_at(lambda b: b.damping, build, jnp.asarray(damping, float))


def _paper(_, build, theta, active, *, cycles, average, settle, control, lanes, driven):
    def one(b, th, on):
        act, ld = b(th)
        r = run_protocol(act, ld, cycles=cycles, average=average, settle=settle,
                         require_settled=False, control=control, lanes=lanes, driven=driven,
                         active=on)
        return jnp.stack([r.P_out, r.P_in]), r.status, r.final_state

    return jax.vmap(one)(build, theta, active)


def _run(build, theta, search: PeakSearch, devices, n_real: int):
    """``(P (K, C, 2): P_out and P_in, status (K, C), final states (K, C, ...))`` of stacked
    builds (leading design axis) at ``theta`` (K, n), for their first ``n_real`` cells (the
    others are padding, not run: :func:`_stacked`)."""
    k = theta.shape[0]
    devices = tuple(devices)[:k]
    rows = padded_cells(0, -(-k // len(devices)) * len(devices), k)  # whole per device

    build = jax.tree_util.tree_map(lambda a: a[rows] if eqx.is_array(a) else a, build)
    _, ld0 = jax.tree_util.tree_map(lambda a: a[0] if eqx.is_array(a) else a,
                                    build)(jnp.asarray(theta[0]))
    n_cells = int(ld0.drive.frequency.shape[0])
    active = np.broadcast_to(np.arange(n_cells) < n_real, (rows.size, n_cells))
    p, status, state = cell_sharded(_paper, devices)(
        None, build, jnp.asarray(theta[rows]), jnp.asarray(active),
        cycles=search.cycles, average=search.average,
        settle=search.early_exit, control=search.control,
        lanes=int(min(n_cells, search.lanes)), driven=driven_membranes(ld0))
    p = np.moveaxis(np.asarray(p)[:k, :, :n_real], 1, -1)
    state = jax.tree_util.tree_map(lambda a: np.asarray(a)[:k, :n_real], state)
    status = np.asarray(status)[:k, :n_real]
    return np.where(status[:, :, None] == 0, p, np.nan), status, state


def _stacked(model, names, case, mass, freq, damping, size: int):
    """Builds of ``case`` for every design (rows of ``freq`` / ``damping``), stacked, each
    padded to ``size`` cells by repeating its last cell.

    Why the padding: a case's coarse and fine stages then have the same shape and share one
    compiled program (the padding cells are not run: :func:`_run`'s ``active``)."""
    def pad(a):
        a = np.asarray(a, float)
        return a[padded_cells(0, size, a.size)]

    return stack_designs([case_builder(model, names, case, mass, pad(f), pad(c))
                          for f, c in zip(freq, damping)])


def _parabola(f, p):
    """Vertex of the parabola through the best of ``p`` (K, G) over ``f`` and its neighbours
    (the best cell itself at the grid's edge or where the fit is not concave)."""
    rows = np.arange(p.shape[0])
    safe = np.where(np.isfinite(p), p, -np.inf)
    best = np.argmax(safe, axis=1)
    i = np.clip(best, 1, p.shape[1] - 2)
    f0, f1 = f[rows, i - 1], f[rows, i]
    p0, p1, p2 = safe[rows, i - 1], safe[rows, i], safe[rows, i + 1]
    h = f1 - f0
    den = p0 - 2.0 * p1 + p2
    with np.errstate(invalid="ignore", divide="ignore"):
        x = 0.5 * (p0 - p2) / den
        ok = (den < 0) & np.isfinite(x) & (np.abs(x) <= 1.0)
        pv = p1 - 0.25 * (p0 - p2) * x
    fb, pb = f[rows, best], safe[rows, best]
    edge = (best == 0) | (best == p.shape[1] - 1)
    use = ok & ~edge
    return np.where(use, f1 + x * h, fb), np.where(use, pv, pb)


def peak_table(models: dict[str, Model], names, theta, *, mass: float, dampings,
               cases=tuple(CASES), search: PeakSearch = PeakSearch(),
               local: dict | None = None, devices=None) -> dict:
    """P_max of every design, case and damping, by the paper protocol.

    **Arguments:**

    - `models`: ``{config name: Model}`` for the configurations of ``cases``.
    - `names`: the varied parameter paths (:mod:`jaxdea.params`), shared by the models.
    - `theta`: ``(K, n)`` values of ``names``, one row per design.
    - `mass`: payload mass M, kg; `dampings`: the payload dampings c, N s/m.
    - `cases`: names in :data:`CASES`.
    - `search`: :class:`PeakSearch`.
    - `local`: ``{(case, c): (f_lo, f_hi)}``: also the largest P_out inside that sub-band of
      the coarse grid (a local maximum, refined like the global one).
    - `devices`: JAX devices to split the designs over (default: all).

    **Returns:**

    ``{"P_max": {case: (K, n_c)}, "f": {case: (K, n_c)}, "P_in": {case: (K, n_c)} (at the
    fine cell nearest the peak), "local": {(case, c): (P (K,), f (K,))}, "state":
    {(case, c, "P" | "L"): the final state
    (K, ...) of the fine cell nearest each peak}, "cells": cells run}``, W and Hz; NaN where
    no cell of a peak's grid reached status 0.
    """
    theta = np.atleast_2d(np.asarray(theta, float))
    k = theta.shape[0]
    devices = tuple(devices or jax.devices())
    cs = np.asarray(dampings, float)
    fc = search.coarse_grid()
    local = dict(local or {})
    out = {"P_max": {}, "f": {}, "P_in": {}, "local": {}, "state": {}, "cells": 0}
    offsets = search.fine * np.arange(-search.half, search.half + 1)
    for name in cases:
        case = CASES[name]
        model = models[case.config]
        ff = np.tile(fc, len(cs))
        cc = np.repeat(cs, fc.size)
        # fine grids: one per damping (global peak) and one per local sub-band, as
        # (local key or None, damping index)
        rows = [row for j, c in enumerate(cs) for row in [(None, j)] + [
            ((ln, lc), j) for ln, lc in local if ln == name and np.isclose(lc, c)]]
        size = max(ff.size, len(rows) * offsets.size)  # both stages in one compiled shape
        build = _stacked(model, names, case, mass, [ff] * k, [cc] * k, size)
        p, _, _ = _run(build, theta, search, devices, ff.size)
        out["cells"] += p.shape[0] * p.shape[1]
        pc = p[..., 0].reshape(k, cs.size, fc.size)
        safe = np.where(np.isfinite(pc), pc, -np.inf)
        centres = []
        for key, j in rows:
            if key is None:
                centres.append(fc[np.argmax(safe[:, j], axis=1)])
            else:
                lo, hi = local[key]
                sub = np.where((fc >= lo) & (fc <= hi), safe[:, j], -np.inf)
                centres.append(fc[np.argmax(sub, axis=1)])
        fine = np.stack([np.clip(c0[:, None] + offsets, search.band[0] * 0.5, None)
                         for c0 in centres], 1)  # (K, R, F)
        damp = np.broadcast_to(np.array([cs[j] for _, j in rows])[None, :, None], fine.shape)
        build = _stacked(model, names, case, mass, fine.reshape(k, -1), damp.reshape(k, -1),
                         size)
        p, _, state = _run(build, theta, search, devices, fine[0].size)
        out["cells"] += p.shape[0] * p.shape[1]
        p = p.reshape(fine.shape + (2,))
        state = jax.tree_util.tree_map(lambda a: a.reshape(fine.shape + a.shape[2:]), state)
        pmax = np.full((k, cs.size), np.nan)
        fmax = np.full((k, cs.size), np.nan)
        pin = np.full((k, cs.size), np.nan)
        for r, (key, j) in enumerate(rows):
            fv, pv = _parabola(fine[:, r], p[:, r, :, 0])
            pv = np.where(np.isfinite(pv), pv, np.nan)
            near = np.abs(fine[:, r] - fv[:, None]).argmin(axis=1)
            out["state"][(name, float(cs[j]), "P" if key is None else "L")] = \
                jax.tree_util.tree_map(lambda a, r=r, near=near: a[np.arange(k), r, near],
                                       state)
            if key is None:
                pmax[:, j], fmax[:, j] = pv, fv
                pin[:, j] = p[np.arange(k), r, near, 1]
            else:
                out["local"][key] = (pv, fv)
        out["P_max"][name], out["f"][name], out["P_in"][name] = pmax, fmax, pin
    return out
