"""Coexisting periodic orbits on a warm-started map: each cell checked against its neighbours
along the masses and along f.

:func:`~jaxdea.engine.warmstart.neighbour_chain` continues every cell's orbit along the map's
second axis (c, from the heaviest load down). Where responses coexist (near a jump, lightly
damped), the orbit so reached depends on the path: the neighbouring mass's orbit at the same
c and f, or the orbit continued along f, may lie on another branch. :func:`coexisting` asks
both:

1. **screen** (masses): the cell's orbit is compared with the orbit predicted from its two
   mass neighbours (same c and f; a secant through the two masses before, through the two
   after for a chunk's first mass, halfway between the masses either side for its second;
   the mass axis is taken as uniform, in value or in log as a geometric grid is); where the
   two are within :data:`SCREEN` (scaled, :func:`~jaxdea.engine.metrics.periodicity_residual`)
   the cell lies on the branch its neighbours are on and nothing more is done. (On the
   heavier chunk of the paper-size map's 1/10 slice, 24 of 116 369 cells are above it.)
2. **iterate**: every other cell runs chord iterations
   (:func:`~jaxdea.engine.chord.chord_cells`, a true Jacobian by one shot first) from its
   nearest mass neighbour's orbit (the mass before; after, for the first), in batches of
   the chain's stage shape (its programs are compiled);
3. **compare**: a cell whose iteration converges to a stable orbit farther than
   :data:`DISTINCT` from its own has two: it is flagged. Its reported orbit stays the one
   continued along c.
4. **continue along f** (:func:`frequency_rows`: a row per mass, damping and phase), up f
   and then down, in steps of at most :data:`F_STEP` of the frequency: where a cell's
   orbit is farther than :data:`SCREEN_F` from the line through the orbits of the two
   cells before it (the one before it, if that is all there is), or where the map has no
   orbit (status not 0) after a cell that has one, the cell is solved from the orbit
   before it (chord iterations from the cell's own Jacobian, the chain's, and where they
   fail from a true one; settling :data:`FOLLOW_CYCLES` periods from it and
   shooting where the map has no orbit there); while that continued orbit is stable and
   not the map's own, the next cell up (down) is solved from it, settling and shooting
   where the chord iterations fail (a branch ended: what a continuation sweep's jump is).
   A cell whose continued orbit is stable and farther than :data:`DISTINCT` from its own
   stable orbit is flagged. This is what finds a hardening resonance's upper branch, which
   the chain along c and both mass neighbours miss (``tests/test_protocols.py``: SCDEA-LS
   with the membrane's viscosity off, M 2 g, c 0.01 N s/m: 152 mW on the branch continued
   up f against the map's 16.1 mW at 84 Hz).

What it cannot see: a branch that none of its neighbours' orbits, continued, reaches (one
reached only from outside the map's frequency range, or only by a path through other
payloads), and, of the mass check, the first stage (the most damped cells, continued along
the masses: their orbits are unique there).
"""

from __future__ import annotations

import jax
import numpy as np

from ..models.cone import ConeActuator, Loading
from .batch import default_lanes, scheduled_batches, take_cells
from .chord import chord_cells
from .metrics import CycleMetrics
from .periodic import flatten_dynamical, periodic_cells, step_residual, with_dynamical
from .sharding import replicated, to_host
from .step_control import StepControl
from .warmstart import chain_layout

#: Scaled distance between a cell's orbit and the one predicted from its mass neighbours
#: above which the cell is iterated from its neighbour's orbit (step 2): a jump between
#: branches, as for :data:`SCREEN_F` (1.4-1.9 between the branches of the hardening
#: resonance). On the heavier chunk of the paper-size map's 1/10 slice (DCDEA-LS, drive A,
#: the 25 heavier masses, 116 369 screened cells) 24 cells are above it (97 above 0.5, 320
#: above 0.3, 5 728 above 3e-2, the first setting, which cost the check 3x the time for
#: no flag).
SCREEN = 0.7
#: Scaled distance between a cell's orbit and the line through the orbits of the two cells
#: before it along f above which the continuation along f starts there (step 4). A jump
#: between branches moves the orbit by O(1) in this norm (at most 2; 0.7 is a component
#: 3.3 times the other's, or of the other sign, as a resonance's phase swing gives): 1.4-1.9
#: between the branches of the hardening resonance in ``tests/test_protocols.py``. On
#: smooth branches it is the grid's extrapolation error, ~h^2: DCDEA-LS, drive A, every 10th
#: mass x every 5th damping of the paper-size map, 0.004 % of the cells are above it on its
#: 0.2 Hz grid (0.07 % above 0.5, 4.5 % above 3e-2: steep resonances), 2.1 % on the 2 Hz
#: grid of ``bench/full_map_slice.py`` (5.2 % above 0.5).
SCREEN_F = 0.7
#: Scaled distance between two converged orbits of one cell above which they are two
#: (converged orbits of one cell agree to the Newton tolerance, ~1e-6).
DISTINCT = 1e-3
#: Largest step of a continuation along f, relative to the frequency: a wider step is no
#: continuation (it steps over the resonances it should follow). Paper 000's 0.2 Hz grid
#: is continued from 4 Hz up, the 2 Hz grid of ``bench/full_map_slice.py`` from 40 Hz up.
F_STEP = 0.05
#: Periods a cell of a continuation along f settles from its seed, where chord iterations
#: from it fail (a branch ended), before it is shot.
FOLLOW_CYCLES = 100


def distance(like, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per cell, the scaled distance between the orbits ``a`` and ``b`` (flat dynamical
    states, ``(n, d)``; ``like``: states of the same cells, host arrays), in the norm of
    :func:`~jaxdea.engine.metrics.periodicity_residual`."""
    n = np.shape(a)[0]
    if not n:
        return np.zeros(0)
    # padded to a power of two (the last cell repeated): the norm's ops compile per shape
    pad = np.minimum(np.arange(1 << (n - 1).bit_length()), n - 1)
    return np.asarray(step_residual(with_dynamical(take_cells(like, pad), a[pad]),
                                    (b - a)[pad]))[:n]


def coexisting(actuator: ConeActuator, loadings: Loading, shape: tuple[int, int, int],
               results: CycleMetrics, *, tol: float = 1e-6,
               control: StepControl = StepControl(), devices: tuple | None = None,
               driven=None, screen: float = SCREEN, screen_f: float = SCREEN_F,
               jacobian: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Which cells of a warm-started block have a second stable orbit (see the module).

    **Arguments:**

    - `actuator`, `loadings`, `shape`, `tol`, `control`, `devices`, `driven`: as given to
      :func:`~jaxdea.engine.warmstart.neighbour_chain`.
    - `results`: what it returned (:class:`CycleMetrics`, host arrays); ``steps`` and
      ``cycles_run`` of the cells iterated here are increased in place by this work.
    - `screen`, `screen_f`: :data:`SCREEN` (masses), :data:`SCREEN_F` (f).
    - `jacobian`: ``(n, d, d)`` each cell's one-period Jacobian at its orbit, NaN where
      unknown (``neighbour_chain(with_jacobian=True)``): a cell continued along f starts
      its chord iterations with its own Jacobian, and needs a true one (a shot, about ten
      periods' work) only where they fail. Default: none known.

    **Returns:**

    ``(flag, iterated)``: bool per cell, true where a second stable orbit was found, and
    true where the cell was solved again (from a mass neighbour's orbit, or in a
    continuation along f).
    """
    devices = tuple(devices or jax.devices()[:1])
    # host arrays, as the chain takes them: a weakly typed leaf would compile its programs anew
    loadings = to_host(loadings)
    shape = tuple(int(k) for k in shape)
    freq = np.asarray(loadings.drive.frequency)
    columns, order = chain_layout(freq, shape, len(devices))
    n = int(np.prod(shape))
    # the chain's stage size (its programs are compiled), or without a chain all cells
    batch = order.size or -(-n // len(devices)) * len(devices)
    kw = dict(tol=float(tol), control=control, devices=devices, driven=driven,
              batch=batch)
    actuator = replicated(actuator, devices)
    # the map's orbits, once for both checks (the checks add work to results, not orbits)
    status = np.asarray(results.status)
    flat = np.asarray(flatten_dynamical(results.final_state))
    chained = np.zeros(n, bool)
    chained[columns[:, :-1].ravel()] = True  # the first stage (last index) excepted
    flag, iterated = _along_masses(actuator, loadings, shape, results, status, flat, chained,
                                   float(screen), **kw)
    two, done = _along_frequency(actuator, loadings, shape, results, status, flat, jacobian,
                                 float(screen_f), **kw)
    return flag | two, iterated | done


def _along_masses(actuator, loadings, shape, results, status, flat, chained, screen, **kw):
    """Steps 1-3 of the module: each chained cell against its mass neighbours' orbits."""
    blocks, n_chain, rest = shape
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
    cand = chained & (status == 0) & (status[partner] == 0) & (status[second] == 0)
    cand &= np.any(flat != flat[partner], axis=1)
    cells = np.nonzero(cand)[0]
    if not cells.size:
        return flag, iterated
    own = take_cells(results.final_state, cells)
    wc = weight[cells, None]
    predicted = wc * flat[partner[cells]] + (1 - wc) * flat[second[cells]]
    cells = cells[distance(own, flat[cells], predicted) > screen]
    iterated[cells] = True
    # a true Jacobian by a shot: from the cell's own, more of these chord iterations fail
    # and run again (more periods per cell on the small maps of tests/test_protocols.py)
    other, conv, _ = solve_from(actuator, loadings, results, cells, flat[partner[cells]],
                                None, **kw)
    flag[cells] = conv & (distance(take_cells(results.final_state, cells), flat[cells], other)
                          > DISTINCT)
    return flag, iterated


def frequency_rows(freq: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray | None:
    """The block's cells as rows along f, ascending: ``(rows, n_f)`` cell indices, a row per
    (mass, damping, phase); the block's last axis is f x phase in C order. ``None`` where the
    frequencies are not one strictly monotonic grid shared by every row."""
    blocks, n_chain, rest = shape
    first = freq[:rest]
    n_phase = int(np.sum(first == first[0]))
    if n_phase < 1 or rest % n_phase:
        return None
    rows = np.arange(blocks * n_chain * rest).reshape(blocks * n_chain, rest // n_phase,
                                                       n_phase)
    rows = rows.transpose(0, 2, 1).reshape(-1, rest // n_phase)
    f = freq[rows]
    rows = rows[:, np.argsort(f[0])]
    f = freq[rows]
    if not ((f == f[:1]).all() and (np.diff(f[0]) > 0).all()):
        return None
    return rows


def _along_frequency(actuator, loadings, shape, results, status, flat, jacobian, screen,
                     **kw):
    """Step 4 of the module: continuation along f, up and down each row, from where the
    map's orbits jump or end."""
    n = int(np.prod(shape))
    flag, iterated = np.zeros(n, bool), np.zeros(n, bool)
    freq = np.asarray(loadings.drive.frequency)
    rows = frequency_rows(freq, shape)
    if rows is None or rows.shape[1] < 2:
        return flag, iterated

    def near(a, b):  # a continuation's step from cell a to cell b
        return np.abs(freq[b] - freq[a]) <= F_STEP * np.minimum(freq[a], freq[b])

    for direction in (rows, rows[:, ::-1]):  # up f, then down
        nxt = np.full(n, -1)
        nxt[direction[:, :-1]] = direction[:, 1:]
        prev, here = direction[:, :-1], direction[:, 1:]
        # the orbit predicted at each cell from the cells before it: a line through the two
        # before it, or the one before it (status 0) where there is no second
        p2 = np.concatenate([prev[:, :1], prev[:, :-1]], axis=1)
        line = (status[p2] == 0) & (p2 != prev)
        span = np.where(line, freq[prev] - freq[p2], 1.0)
        w = np.where(line, (freq[here] - freq[p2]) / span, 1.0)
        predicted = w[..., None] * flat[prev] + (1 - w[..., None]) * flat[p2]
        ok = status[prev] == 0
        off = np.zeros(here.shape, bool)
        both = ok & (status[here] == 0)
        off[both] = distance(take_cells(results.final_state, here[both]), flat[here[both]],
                             predicted[both]) > screen
        start = ok & (off | (status[here] != 0)) & near(prev, here)
        cells, seeds = here[start], flat[prev[start]]
        jacs = None if jacobian is None else jacobian[cells]
        following = False
        while cells.size:
            iterated[cells] = True
            # settle where the map has no orbit, or along a branch the map is not on
            settle = (status[cells] != 0) | following
            orbits, conv, jacs = solve_from(actuator, loadings, results, cells, seeds, jacs,
                                            settle=settle, **kw)
            mine = status[cells] == 0
            gap = np.full(cells.size, np.inf)
            gap[mine] = distance(take_cells(results.final_state, cells[mine]), flat[cells[mine]],
                                 orbits[mine])
            flag[cells] |= conv & mine & (gap > DISTINCT)
            go = conv & (gap > DISTINCT) & (nxt[cells] >= 0)
            go &= near(cells, np.maximum(nxt[cells], 0))
            cells, seeds, jacs, following = nxt[cells[go]], orbits[go], jacs[go], True
    return flag, iterated


def solve_from(actuator: ConeActuator, loadings: Loading, results: CycleMetrics,
               cells: np.ndarray, seeds: np.ndarray, jacobians: np.ndarray | None, *,
               batch: int, tol: float, control: StepControl, devices: tuple, driven,
               settle: np.ndarray | None = None):
    """Stable periodic orbits of the distinct ``cells`` from the flat states ``seeds``.

    Chord iterations (:func:`~jaxdea.engine.chord.chord_cells`) in batches of ``batch``
    cells (a compiled stage shape), from the Jacobians ``jacobians`` (``(len(cells), d,
    d)``, or ``None``: none known) where they are finite, and where those fail or are not
    finite from a true one (by one shot); where both fail and ``settle`` is true, the cell
    settles from its seed for :data:`FOLLOW_CYCLES` periods and is shot
    (:func:`~jaxdea.engine.periodic.periodic_cells`, its stability checked): what a
    continuation along f does where a branch ends. The work is added to the cells'
    ``steps`` and ``cycles_run`` in ``results`` (in place).

    Returns ``(orbits, converged, jacobians)``: flat dynamical states ``(len(cells), d)``, a
    bool per cell, true where a stable orbit was found (elsewhere the orbit is
    meaningless), and the Jacobians the chord iterations ended with (NaN where the cell
    settled).
    """
    n_dev = len(devices)
    freq = np.asarray(loadings.drive.frequency)
    d = seeds.shape[1]
    orbits, converged = np.full((cells.size, d), np.nan), np.zeros(cells.size, bool)
    ended = np.full((cells.size, d, d), np.nan)
    where = np.full(freq.size, -1)
    where[cells] = np.arange(cells.size)
    lanes = default_lanes(batch // n_dev, devices)
    kw = dict(tol=tol, control=control, lanes=lanes, devices=devices, driven=driven)

    def solve(todo, how):
        for sub, real in scheduled_batches(cells[todo], batch, freq, n_dev):
            start = with_dynamical(take_cells(results.final_state, sub), seeds[where[sub]])
            r, jac, conv = how(take_cells(loadings, sub), start, sub, real)
            r = to_host(r)
            for k in ("steps", "cycles_run"):  # a cell's work counts all it took
                total = getattr(results, k)
                total[sub[real]] += np.asarray(getattr(r, k))[real].astype(total.dtype)
            mine = where[sub[real]]
            orbits[mine] = np.asarray(flatten_dynamical(r.final_state))[real]
            converged[mine] = conv[real]
            ended[mine] = np.asarray(jac)[real]

    def chord(known):
        return lambda ld, start, sub, real: chord_cells(
            actuator, ld, start, np.asarray(jacobians[where[sub]], np.float64) if known else
            np.full((sub.size, d, d), np.nan), active=real, **kw)[:3]

    def settled(ld, start, sub, real):
        r = periodic_cells(actuator, ld, initial=start, active=real, warmup=FOLLOW_CYCLES, **kw)
        return r, np.full((sub.size, d, d), np.nan), np.asarray(r.status) == 0

    if jacobians is not None:
        solve(np.isfinite(jacobians).all(axis=(1, 2)), chord(True))
    solve(~converged, chord(False))
    if settle is not None:
        solve(~converged & settle, settled)
    return orbits, converged, ended
