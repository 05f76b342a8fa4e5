"""A host-side solver as a differentiable JAX function (``jax.custom_jvp``).

The steady-state design objectives (:mod:`jaxdea.engine.sensitivity`) solve on the host:
settling, Newton iterations and the implicit derivatives of the orbit are numpy around
jitted engine calls. :func:`implicit` makes such a solver ``theta -> (values, jacobians)``
a JAX function: forward mode uses the Jacobians, and ``jax.grad`` / ``jax.jacrev`` work by
JAX's transposition of that linear tangent rule.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

try:  # eval_context: see host_eval
    from jax._src import core as jax_core
except ImportError:  # pragma: no cover - a JAX that moved its internals
    jax_core = None


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def implicit(solve: Callable, theta):
    """A host-side solver as a differentiable JAX function of ``theta``.

    **Arguments:**

    - `solve`: ``theta (concrete numpy (n,)), need_jac -> (values, jacobians)``: ``values``
      a dict of arrays, ``jacobians`` the same keys with one more trailing axis of size n
      (None when ``need_jac`` is false). Keys whose jacobian is None (e.g. a status) get a
      zero tangent.
    - `theta`: ``(n,)`` parameters (concrete, or a JAX autodiff tracer of concrete values).

    **Returns:**

    ``values`` as JAX arrays; differentiable in forward (``jax.jvp``, ``jax.jacfwd``) and
    reverse mode (``jax.grad``, ``jax.jacrev``; the tangent rule is linear in the tangent).
    """
    with host_eval():  # the host solver computes eagerly
        values, _ = solve(_concrete(theta), False)
    return {k: jnp.asarray(v) for k, v in values.items()}


@implicit.defjvp
def _implicit_jvp(solve, primals, tangents):
    (theta,), (dtheta,) = primals, tangents
    with host_eval():  # the host solver computes eagerly
        values, jacs = solve(_concrete(theta), True)
    out = {k: jnp.asarray(v) for k, v in values.items()}
    tan = {}
    for k, v in out.items():
        j = None if jacs is None else jacs.get(k)
        tan[k] = jnp.zeros_like(v) if j is None else jnp.asarray(j) @ dtheta
    return out, tan


def host_eval():
    """A context in which JAX computes eagerly, also inside a trace (a custom rule that
    ``jax.grad`` stages): the host solvers' jitted engines then run on concrete arrays.

    ``jax.ensure_compile_time_eval`` does this by setting the ``eager_constant_folding``
    flag, which is part of every jit's cache key: each engine program called inside it was
    compiled a second time (~10 s each for a shot) beside the one that the same engine uses
    outside ``jax.grad``. JAX's evaluation context runs the calls eagerly with the flag
    unchanged, so both share one compiled program. Falls back to the public context manager
    on a JAX without it (correct, only compiling twice).
    """
    context = getattr(jax_core, "eval_context", None)
    return context() if context is not None else jax.ensure_compile_time_eval()


def _concrete(theta) -> np.ndarray:
    try:
        return np.asarray(theta, dtype=float)
    except jax.errors.TracerArrayConversionError:
        raise TypeError("the steady-state objectives solve on the host: call them under "
                        "jax.grad / jax.jacfwd / jax.jacrev, not under jax.jit or vmap") from None
