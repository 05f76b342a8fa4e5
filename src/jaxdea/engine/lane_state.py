"""What a lane of the engine carries (:class:`Lane`), and the small helpers on cells' states.

:func:`jaxdea.engine.lanes.run_protocol` runs a pool of these lanes over a queue of cells;
the periodic protocol's stages (:mod:`jaxdea.engine.periodic`, :mod:`jaxdea.engine.warmstart`)
select and restart cells' states with the helpers here.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..models.cone import ConeState, Loading
from .metrics import Dynamics, Energies


def cycle_nodes(loading: Loading) -> Array:
    """Sorted step boundaries within one period, as fractions in (0, 1]: every edge and 1."""
    e = loading.drive.edge_fractions()
    e = jnp.where(e < 1e-12, 1.0, e)
    return jnp.sort(jnp.concatenate([e, jnp.ones(1)]))


def first_step(dt_max, frequency: Array) -> Array:
    """The step a cell starts with, s: a 200th of its period, at most ``dt_max``."""
    return jnp.minimum(dt_max, 1.0 / frequency / 200.0)


def select_cells(mask: Array, a, b):
    """Per cell (leading axis), ``a``'s leaves where ``mask`` is true, else ``b``'s."""
    return jax.tree_util.tree_map(
        lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


@jax.custom_jvp
def _set_rows(out: Array, index: Array, rows: Array) -> Array:
    return out.at[index].set(rows, mode="drop")


@_set_rows.defjvp
def _set_rows_jvp(primals, tangents):
    # the tangent is set at the same rows through its own copy of the index (a scatter
    # sharing the primal's index is a sibling, see scatter_each); JAX's own rule for a
    # scatter that may repeat an index adds scatter-adds of the same index. Declared unique
    # (scatter_each's callers' in-bound indices are) so that reverse mode can transpose it.
    out, index, rows = primals
    d_out, _, d_rows = tangents
    own = jax.lax.optimization_barrier(index)
    d = d_out.at[own].set(d_rows, mode="drop", unique_indices=True)
    return _set_rows(out, index, rows), d


def scatter_each(out, index: Array, values):
    """``out.at[index].set(values, mode="drop")`` leaf by leaf (``out`` and ``values`` pytrees
    of one structure), each scatter, and each scatter's tangent, with its own copy of
    ``index``. Its in-bound entries must be distinct (out-of-bound ones, dropped, may
    repeat), as in the engine's uses: reverse mode transposes the tangent as a gather.

    Why: XLA's CPU multi-output fusion (:data:`~jaxdea.engine.sharding.MULTI_OUTPUT_FUSION`)
    merges sibling scatters of one index into a kernel that its emitter aborts on (jaxlib
    0.10.2: a failed check in ``symbolic_map.cc``, which kills the process); behind an
    optimisation barrier each scatter has an index of its own and stays a kernel of its own,
    as without the option. Same values either way.
    """
    leaves, tree = jax.tree_util.tree_flatten(out)
    indices = jax.lax.optimization_barrier([index] * len(leaves))
    return jax.tree_util.tree_unflatten(tree, [
        _set_rows(o, i, v)
        for o, i, v in zip(leaves, indices, tree.flatten_up_to(values), strict=True)])


def reset_accumulators(y: ConeState) -> ConeState:
    """``y`` with the energy integrals set to zero (a new cell starts its own bookkeeping)."""
    return eqx.tree_at(lambda s: (s.payload_work, s.v2, s.energy_in), y,
                       (jnp.zeros_like(y.payload_work), jnp.zeros_like(y.v2),
                        jnp.zeros_like(y.energy_in)))


class Lane(eqx.Module):
    """One lane of the engine's pool (vmapped: every field has the pool's leading axis)."""

    job: Array  # cell index, or n_cells when idle
    y: ConeState
    loading: Loading
    nodes: Array  # sorted step boundaries within a cycle (fractions, last = 1)
    cycle: Array  # completed cycles
    budget: Array  # the cell's cycles (``cycles``)
    average: Array  # the cell's cycles averaged at the end of its budget (``average``)
    u: Array  # current position in the cycle, fraction in [0, 1)
    h: Array  # proposed next step, s
    steps: Array
    window: Energies  # energy accumulators at the start of the averaging window
    wcycle: Array  # completed cycles when the averaging window started
    prev: Dynamics  # dynamical states at the start of the current cycle
    res: Array  # periodicity residual of the last completed cycle
    ratio: Array  # residual of the last cycle over that of the one before
    rate: Array  # contraction per cycle: the larger of the last two ratios
    back: Array  # energy returned to each driven source in the window (<= 0), J
    xmin: Array
    xmax: Array
    lockup: Array
    blown: Array  # the step size collapsed; the state becomes NaN at the round's end
    done: Array
    history: Array  # cycle-start states for the transient's extrapolation (empty when off)
    recorded: Array  # the last cycle whose start state is in history (empty when off)
    streak: Array  # consecutive cycle-start states in history; < 0 after a jump (empty: off)
    origin: Array  # the cycle-start state a lane jumped from, flattened (empty when off)
    landing: Array  # the state it jumped to, flattened (empty when off)
    jumped_from: Array  # the cycle it jumped from until the jump is checked, else -1
    expect: Array  # the difference the fit predicted after the landing (empty when off)
    guess: Array  # the lane's last prediction of its jump's landing, flattened (empty: off)
    guessed: Array  # the cycle that prediction was made at, else -1 (empty when off)
    hwrap: Array  # the step proposed at the last cycle end, s: a jump's (empty when off)


def rest_states(model, loadings: Loading) -> ConeState:
    """The rest state of every cell (leading axis = cells): the static equilibrium with the
    cell's payload on (:meth:`~jaxdea.models.cone.ConeActuator.initial_state`). Without a
    payload that loads the disk at rest every cell rests at the same state."""
    n = jax.tree_util.tree_leaves(loadings)[0].shape[0]
    if not loadings.payload.loads_at_rest:
        rest = model.initial_state()
        return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), rest)
    return jax.vmap(model.initial_state)(loadings.payload)
