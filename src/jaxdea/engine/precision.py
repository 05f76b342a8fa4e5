"""Single-precision lanes: what is narrowed to float32, and what stays float64.

Narrowed (``precision="single"``, :class:`~jaxdea.engine.step_control.StepControl`): the
dynamical states (:data:`~jaxdea.engine.metrics.DYNAMICAL`: disk positions and velocities,
charges, dashpot stretches) and the parameters of the actuator and of the payload law, so
the vector field, the RK stages and the step-error norm run on float32 vectors (twice the
SIMD width; what that buys on a CPU is measured in ``bench/precision_bench.py`` and
``bench/NOTES.md``).

Kept in float64: time and step sizes (the stage times are nudged 1e-9 of a step inside the
step so that a square-wave edge on a step boundary belongs to the right side; float32 would
lose that nudge, and the phase of cycle 100), the drive itself (its value is narrowed where
the model uses it), and the energy integrals (payload work, ``v^2``, ``Phi i``): a cycle
average is the difference of two integrals over 100 cycles, and float32 sums of ~1e4
increments would lose the digits the average needs. The static equilibrium (the rest state)
is solved in float64 and then narrowed.

Single-precision lanes stop the per-cycle charge weight (``step_control.charge_weight``,
down to 3e-3 at 1 Hz in double precision) at :data:`SINGLE_CHARGE_WEIGHT_MIN`: a tighter
weight asks for charges finer than float32 resolves (with the 2 Hz weight a float32 cell
took 1.6x the steps of float64, fighting rounding). Below ~10 Hz their P_in without
recovery is therefore further from LSODA than double's (measured in
``bench/precision_bench.py``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import SweepError
from ..models.cone import ConeState
from .metrics import DYNAMICAL

#: The states single-precision lanes hold in float32: all dynamical states.
NARROWED = DYNAMICAL


def narrow(tree):
    """``tree`` with every floating array leaf in float32 (the actuator's and the payload
    law's parameters)."""
    return jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32)
        if eqx.is_array(a) and jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


def narrow_states(y: ConeState) -> ConeState:
    """``y`` with its dynamical states in float32; the energy integrals stay float64."""
    return eqx.tree_at(lambda s: tuple(getattr(s, n) for n in NARROWED), y,
                       tuple(getattr(y, n).astype(jnp.float32) for n in NARROWED))


def widen_states(y: ConeState) -> ConeState:
    """``y`` with every leaf in float64 (results leave the engine in double precision)."""
    return jax.tree_util.tree_map(lambda a: a.astype(jnp.float64), y)


#: Smallest ``rtol`` of single-precision lanes: a step's error estimate (a difference of two
#: stages) is only resolved down to a few float32 ulps of the charge (its weight is 1e-1).
#: Measured (DCDEA-LS, 128 payloads at 60 Hz, 40 cycles): rtol 1e-6 takes the same steps in
#: float32 as in float64 (721 k vs 720 k) and agrees to 2e-5 on P_out.
SINGLE_RTOL_MIN = 1e-6
#: Smallest charge error weight of single-precision lanes (the weight of 9 Hz cells).
SINGLE_CHARGE_WEIGHT_MIN = 3e-2


#: Smallest early exit of single-precision lanes: the periodicity residual of a float32 cycle
#: stalls at ~1e-5 (measured, DCDEA-LS at 60 Hz: median 7e-6 against 5e-10 in float64), so a
#: tighter early exit is never reached and every cell would run all its cycles.
SINGLE_EARLY_EXIT_MIN = 1e-5


def check_precision(control, protocol: str, early_exit) -> None:
    """Refuse settings that single-precision lanes cannot honour (before any computation).

    **Arguments:**

    - `control`: the :class:`~jaxdea.engine.step_control.StepControl` (already checked).
    - `protocol`: the protocol's name.
    - `early_exit`: the paper protocol's early exit (``None``: none).

    **Returns:**

    Nothing; raises :class:`~jaxdea.SweepError` naming the setting otherwise.
    """
    if control.precision != "single":
        return
    if control.rtol < SINGLE_RTOL_MIN:
        raise SweepError(f"rtol = {control.rtol!r} is below what single precision resolves "
                         f"(allowed range [{SINGLE_RTOL_MIN:g}, 1) with precision='single')")
    if protocol == "periodic":
        raise SweepError("precision = 'single' runs the paper and continuation protocols; "
                         "protocol='periodic' needs 'double' (its Newton step and its tol "
                         f"are below the periodicity float32 lanes resolve, ~"
                         f"{SINGLE_EARLY_EXIT_MIN:g})")
    if early_exit is not None and early_exit < SINGLE_EARLY_EXIT_MIN:
        raise SweepError(f"early_exit = {early_exit!r} is below the periodicity float32 lanes "
                         f"resolve: with precision='single' the allowed range is "
                         f"[{SINGLE_EARLY_EXIT_MIN:g}, 1), or None (every cell runs all "
                         f"its cycles)")
