"""Coexisting periodic orbits on a warm-started map: each cell checked against a second neighbour.

:func:`~jaxdea.engine.warmstart.neighbour_chain` continues every cell's orbit along the map's
second axis (c, from the heaviest load down). Where responses coexist (near a jump, lightly
damped), the orbit so reached depends on the path: the neighbouring mass's orbit at the same
c and f may lie on another branch. :func:`coexisting` asks each chained cell's second
neighbour:

1. **screen**: the cell's orbit is compared with the orbit predicted from its two mass
   neighbours (same c and f; a secant through the two masses before, through the two after
   for a chunk's first mass, halfway between the masses either side for its second; the
   mass axis is taken as uniform, in value or in log as a geometric grid is); where the two
   are within :data:`SCREEN` (scaled, :func:`~jaxdea.engine.metrics.periodicity_residual`)
   the cell lies on the branch its neighbours are on and nothing more is done. (On the
   paper-size map's 1/10 slice the secant is within the screen for 97 % of the cells; the
   nearest neighbour alone for 81 %.)
2. **iterate**: every other cell runs chord iterations
   (:func:`~jaxdea.engine.chord.chord_cells`, a true Jacobian by one shot first) from its
   nearest mass neighbour's orbit (the mass before; after, for the first), in batches of
   the chain's stage shape (its programs are compiled);
3. **compare**: a cell whose iteration converges to a stable orbit farther than
   :data:`DISTINCT` from its own has two: it is flagged. Its reported orbit stays the one
   continued along c.

What it cannot see: a branch that neither neighbour is on, and the first stage (the most
damped cells, continued along the masses: their orbits are unique there).
"""

from __future__ import annotations

import jax
import numpy as np

from ..models.cone import ConeActuator, Loading
from .batch import default_lanes, scheduled_batches, take_cells
from .chord import chord_cells
from .metrics import CycleMetrics
from .periodic import flatten_dynamical, step_residual, with_dynamical
from .sharding import replicated, to_host
from .step_control import StepControl
from .warmstart import chain_layout

#: Scaled distance between a cell's orbit and the one predicted from its mass neighbours
#: above which the cell is iterated from its neighbour's orbit (step 2). On the paper-size
#: map's 1/10 slice (DCDEA-LS, drive A) 3 % of the chained cells are above it.
SCREEN = 3e-2
#: Scaled distance between two converged orbits of one cell above which they are two
#: (converged orbits of one cell agree to the Newton tolerance, ~1e-6).
DISTINCT = 1e-3


def distance(like, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per cell, the scaled distance between the orbits ``a`` and ``b`` (flat dynamical
    states, ``(n, d)``; ``like``: states of the same cells, host arrays), in the norm of
    :func:`~jaxdea.engine.metrics.periodicity_residual`."""
    return np.asarray(step_residual(with_dynamical(like, a), b - a))


def coexisting(actuator: ConeActuator, loadings: Loading, shape: tuple[int, int, int],
               results: CycleMetrics, *, tol: float = 1e-6,
               control: StepControl = StepControl(), devices: tuple | None = None,
               driven=None, screen: float = SCREEN) -> tuple[np.ndarray, np.ndarray]:
    """Which cells of a warm-started block have a second stable orbit (see the module).

    **Arguments:**

    - `actuator`, `loadings`, `shape`, `tol`, `control`, `devices`, `driven`: as given to
      :func:`~jaxdea.engine.warmstart.neighbour_chain`.
    - `results`: what it returned (:class:`CycleMetrics`, host arrays); ``steps`` and
      ``cycles_run`` of the cells iterated here are increased in place by this work.
    - `screen`: :data:`SCREEN`.

    **Returns:**

    ``(flag, iterated)``: bool per cell, true where a second stable orbit was found, and
    true where the cell was iterated (step 2).
    """
    devices = tuple(devices or jax.devices()[:1])
    n_dev = len(devices)
    # host arrays, as the chain takes them: a weakly typed leaf would compile its programs anew
    loadings = to_host(loadings)
    blocks, n_chain, rest = (int(k) for k in shape)
    n = blocks * n_chain * rest
    flag, iterated = np.zeros(n, bool), np.zeros(n, bool)
    if blocks < 2:
        return flag, iterated
    idx = np.arange(n).reshape(blocks, n_chain, rest)
    partner = idx[np.r_[1, np.arange(blocks - 1)]].ravel()  # the mass before (after, first)
    # the screen's prediction: a secant through the partner and a second neighbour,
    # x = w * x[partner] + (1 - w) * x[second]
    if blocks > 2:
        b = np.r_[2, 2, np.arange(0, blocks - 2)]
        w = np.r_[2.0, 0.5, np.full(blocks - 2, 2.0)]
    else:
        b, w = np.r_[1, 0], np.ones(2)
    second = idx[b].ravel()
    weight = np.broadcast_to(w[:, None, None], (blocks, n_chain, rest)).ravel()
    freq = np.asarray(loadings.drive.frequency)
    columns, order = chain_layout(freq, shape, n_dev)
    checked = np.zeros(n, bool)
    checked[columns[:, :-1].ravel()] = True  # chained, the first stage (last index) excepted
    status = np.asarray(results.status)
    flat = np.asarray(flatten_dynamical(results.final_state))
    cand = checked & (status == 0) & (status[partner] == 0) & (status[second] == 0)
    cand &= np.any(flat != flat[partner], axis=1)
    cells = np.nonzero(cand)[0]
    if not cells.size:
        return flag, iterated
    own = take_cells(results.final_state, cells)
    wc = weight[cells, None]
    predicted = wc * flat[partner[cells]] + (1 - wc) * flat[second[cells]]
    far = distance(own, flat[cells], predicted) > float(screen)
    cells = cells[far]
    iterated[cells] = True
    actuator = replicated(actuator, devices)
    batch = order.size  # the chain's stage size: its programs are compiled
    lanes = default_lanes(batch // n_dev, devices)
    for sub, real in scheduled_batches(cells, batch, freq, n_dev):
        seed = take_cells(results.final_state, sub)
        start = with_dynamical(seed, flat[partner[sub]])
        jac = np.full((batch,) + (flat.shape[1],) * 2, np.nan)
        r, _, conv = chord_cells(actuator, take_cells(loadings, sub), start, jac,
                                 tol=tol, control=control, lanes=lanes, devices=devices,
                                 driven=driven, active=real)
        r = to_host(r)
        other = np.asarray(flatten_dynamical(r.final_state))
        two = conv & (distance(seed, flat[sub], other) > DISTINCT)
        mine = sub[real]
        flag[mine] = two[real]
        for k in ("steps", "cycles_run"):  # a cell's work counts all it took
            total = getattr(results, k)
            total[mine] += np.asarray(getattr(r, k))[real].astype(total.dtype)
    return flag, iterated
