"""Transient driver of the viscoelastic models (mass cone of papers 001/002, planar DEA of 004).

The one place these models meet ``diffrax``. A model is an ``eqx.Module`` with

- ``initial_state()`` -> state pytree (the static prestretched state, Phi = 0);
- ``vector_field(t, y, signal)`` -> d y / d t, ``signal(t)`` being the voltage (V);
- ``observables(t, y, signal)`` -> dict of scalars: ``displacement`` (m, from the
  prestretched state), ``voltage`` (V) and the stretches.

Stiffness: relaxation times from 1e-4 s (paper 001's Kelvin elements) or 0.01 s (paper 002)
to thousands of seconds, plus the membrane-inertia mode of the cone (~540 Hz), so the default
solver is the L-stable implicit ESDIRK ``diffrax.Kvaerno5`` with a PI step-size controller
(``pcoeff=0.3, icoeff=0.4``: far fewer rejections on these stiff problems) whose step
boundaries are put on every kink of the drive (``jump_ts``: the triangular and multi-sine
drives have derivative jumps, and paper 004's eq 15 uses ``dPhi/dt``). A model may define
``error_norm`` (used by the controller and the chord iteration): the mass cone weighs its
stretch rate by 1 ms, without which the lightly damped ~540 Hz membrane-inertia mode
keeps the steps at ~0.3 ms (1500 steps per simulated second instead of ~90). Validated
against scipy Radau/LSODA at rtol 1e-10 (tests/test_planar.py, tests/test_mass_cone.py).

For gradients w.r.t. parameters use ``fixed_steps``: a fixed step grid (with the drive kinks
and the output times merged in) makes the discrete solution a smooth function of the
parameters, so reverse-mode derivatives (``RecursiveCheckpointAdjoint``) match finite
differences to ~1e-7; the adaptive mode is also differentiable, but its step-size choices
make finite differences noisy (~1e-3). Caveat: paper 004's rhs has ``dPhi/dt``; a fixed step
ending on a drive kink sees the next segment's slope in its last stage (first-order error:
3 % at 160 steps per 4-s VP1 cycle), so use the adaptive mode or many steps there.
"""

from __future__ import annotations

import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import xarray as xr
from jaxtyping import Array, ArrayLike

__all__ = ["solve", "displacement", "transient", "amplitude_frequency", "hysteresis_area"]


class _QuietChord(diffrax.VeryChord):
    """``diffrax.VeryChord`` whose convergence test ignores round-off.

    The stock test divides successive increments to estimate the contraction rate; when the
    stage solution is already exact (steady states, or tight tolerances) the increments are
    round-off, the rate is noise, and the iteration is declared divergent or unconverged, so
    every step is rejected (adaptive: the step size collapses; fixed steps: the solve fails).
    Here an increment below ``1e-3`` of the tolerance counts as converged and divergence is
    only declared for increments above the tolerance.
    """

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        at_least_two = state.step >= 2
        rate = state.diffsize / state.diffsize_prev
        factor = state.diffsize * rate / (1 - rate)
        tiny = state.diffsize < 1e-3
        diverged = (state.diffsize > 1.0) & (jnp.invert(jnp.isfinite(rate)) | (rate > 2))
        converged = tiny | ((factor > 0) & (factor < self.kappa))
        terminate = at_least_two & (converged | diverged)
        result = optx.RESULTS.where(at_least_two & jnp.invert(converged),
                                    optx.RESULTS.nonlinear_divergence,
                                    optx.RESULTS.successful)
        linsolve_fail = state.result != optx.RESULTS.successful
        result = optx.RESULTS.where(linsolve_fail, state.result, result)
        return linsolve_fail | terminate, result


def _root_finder(rtol: float, atol: float, norm=optx.rms_norm) -> diffrax.VeryChord:
    return _QuietChord(rtol=rtol, atol=atol, kappa=0.5, norm=norm)


def _norm(model):
    """The model's error norm (``model.error_norm``, e.g. the mass cone weighs its velocity
    by a time scale) or the RMS norm."""
    return getattr(model, "error_norm", optx.rms_norm)


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _cycles(signal, t_end: float) -> int:
    return int(math.ceil(float(t_end) / float(signal.period) - 1e-9)) + 1


def _step_grid(signal, ts: np.ndarray, fixed_steps: int) -> np.ndarray:
    """Uniform grid of ``fixed_steps`` steps over ``[ts[0], ts[-1]]``, with the output times
    and the drive kinks merged in (so no step straddles a kink)."""
    t0, t1 = float(ts[0]), float(ts[-1])
    kinks = np.asarray(signal.kink_times(_cycles(signal, t1)))
    kinks = kinks[(kinks > t0) & (kinks < t1)]
    grid = np.unique(np.concatenate([np.linspace(t0, t1, fixed_steps + 1), ts, kinks]))
    keep = np.concatenate([[True], np.diff(grid) > 1e-9 * max(1.0, abs(t1))])
    grid = grid[keep]
    grid[-1] = t1
    return grid


@eqx.filter_jit
def _solve(model, signal, ts, jump_ts, step_ts, rtol, atol, max_steps):
    term = diffrax.ODETerm(model.vector_field)
    norm = _norm(model)
    if step_ts is None:
        solver = diffrax.Kvaerno5(root_finder=_root_finder(rtol, atol, norm))
        controller = diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=rtol, atol=atol, pcoeff=0.3, icoeff=0.4, norm=norm),
            jump_ts=jump_ts)
        dt0 = None
    else:
        # optimistix's plain Chord: the VeryChord family declares divergence on the step
        # after a drive kink in paper 004's model (whose rhs has dPhi/dt) and a fixed grid
        # cannot retry with a smaller step
        solver = diffrax.Kvaerno5(root_finder=optx.Chord(rtol=rtol, atol=atol, norm=norm),
                                  root_find_max_steps=30)
        controller = diffrax.StepTo(ts=step_ts)
        dt0 = None
    sol = diffrax.diffeqsolve(
        term, solver, t0=ts[0], t1=ts[-1], dt0=dt0, y0=model.initial_state(), args=signal,
        saveat=diffrax.SaveAt(ts=ts), stepsize_controller=controller, max_steps=max_steps,
        throw=False,
    )
    obs = jax.vmap(lambda t, y: model.observables(t, y, signal))(sol.ts, sol.ys)
    return sol.ys, obs, sol.result == diffrax.RESULTS.successful


def solve(model, signal, ts: ArrayLike, *, rtol: float = 1e-8, atol: float = 1e-10,
          fixed_steps: int | None = None, max_steps: int = 200_000,
          jump_ts: ArrayLike | None = None) -> tuple[Any, dict, Array]:
    """Integrate ``model`` under ``signal`` from its prestretched state; save at ``ts`` (s).

    **Arguments:**

    - `model`: a viscoelastic model (:class:`~jaxdea.MassCone`, :class:`~jaxdea.PlanarDEA`);
      its parameters may be traced (jit/grad/vmap over the model).
    - `signal`: the drive voltage (:mod:`jaxdea.signals`).
    - `ts`: output times, s; concrete (a numpy array) unless ``jump_ts`` is given.
    - `rtol`, `atol`: tolerances of the adaptive controller; `max_steps`: step budget.
    - `fixed_steps`: use that many uniform steps (plus kinks and ``ts``) instead of the
      adaptive controller (for exact gradients, see the module docstring).
    - `jump_ts`: the signal's kinks, when ``ts`` is traced.

    **Returns:**

    ``(ys, observables, ok)``: the states and the observables at ``ts`` and a success flag
    (False: step budget exhausted or the implicit solve failed, e.g. Gent lock-up; the
    outputs are then not trustworthy).
    """
    # the step grid / kinks come from the (concrete) drive and ts, also inside a jit trace
    with jax.ensure_compile_time_eval():
        if fixed_steps is not None:
            ts_np = np.asarray(ts, dtype=float)
            step_ts = jnp.asarray(_step_grid(signal, ts_np, int(fixed_steps)))
            max_steps = int(step_ts.shape[0]) + 1
            jump = None
        else:
            step_ts = None
            if jump_ts is None:
                jump_ts = signal.kink_times(_cycles(signal, float(np.asarray(ts)[-1])))
            jump = jnp.asarray(jump_ts)
    ts = jnp.asarray(ts, dtype=float)
    return _solve(model, signal, ts, jump, step_ts, rtol, atol, max_steps)


def displacement(model, signal, ts: ArrayLike, **kwargs) -> Array:
    """Displacement (m) from the prestretched state at the times ``ts`` (s).

    The function to fit by gradient: differentiable w.r.t. every model parameter (and the
    signal's); ``kwargs`` as in :func:`solve` (``fixed_steps=...`` for exact gradients).
    """
    return solve(model, signal, ts, **kwargs)[1]["displacement"]


def transient(model, signal, ts: ArrayLike, *, name: str = "", **kwargs) -> xr.Dataset:
    """:func:`solve` as a labelled Dataset.

    **Arguments:**

    - `model`, `signal`, `ts`: as in :func:`solve`.
    - `name`: stored as ``attrs["model"]``.
    - `kwargs`: passed to :func:`solve`.

    **Returns:**

    An ``xarray.Dataset`` over ``t`` (s): ``voltage`` (V), ``displacement`` (m, from the
    prestretched state) and the stretches; ``attrs["ok"]`` says whether the solve succeeded.
    """
    _, obs, ok = solve(model, signal, ts, **kwargs)
    units = {"voltage": "V", "displacement": "m"}
    data = {k: xr.Variable(("t",), np.asarray(v), {"units": units.get(k, "1")})
            for k, v in obs.items()}
    return xr.Dataset(data, coords={"t": xr.Variable(("t",), np.asarray(ts, float),
                                                     {"units": "s"})},
                      attrs={"model": name, "ok": int(bool(ok))})


@eqx.filter_jit
def _afr(model, freqs, amplitude, cycles, points, rtol, atol, max_steps):
    from ..signals import MultiSine

    def one(f):
        signal = MultiSine(jnp.reshape(amplitude, (1,)), jnp.reshape(f, (1,)))
        last = (cycles - 1 + jnp.linspace(0.0, 1.0, points)) / f
        ts = jnp.concatenate([jnp.zeros(1), last])
        jump = jnp.arange(cycles + 1) / f
        ys, obs, ok = _solve(model, signal, ts, jump, None, rtol, atol, max_steps)
        z = obs["displacement"][1:]
        return 0.5 * (jnp.max(z) - jnp.min(z)), ok

    return jax.vmap(one)(freqs)


def amplitude_frequency(model, freqs: ArrayLike, amplitude: ArrayLike, *, cycles: int = 4,
                        points: int = 201, rtol: float = 1e-7, atol: float = 1e-10,
                        max_steps: int = 100_000) -> tuple[Array, Array]:
    """Amplitude-frequency response (paper 002 Fig 13), one ``vmap``-ed solve over ``freqs``.

    Each frequency ``f`` (Hz) drives the model from its prestretched state with the eq-25 wave
    of one segment, ``v = amplitude |sin(pi f t)|`` (period ``1/f``), for ``cycles`` periods;
    the amplitude is half the peak-to-peak displacement over the last period, sampled at
    ``points`` instants. Returns ``(amplitude_m, ok)`` per frequency.
    """
    freqs = jnp.asarray(freqs, dtype=float)
    return _afr(model, freqs, jnp.asarray(amplitude, float), int(cycles), int(points),
                rtol, atol, max_steps)


def hysteresis_area(voltage: ArrayLike, disp: ArrayLike) -> Array:
    """Signed area of the displacement-voltage loop, ``-oint z dV = oint V dz`` (V m), by the
    trapezoidal rule over the given samples (one closed cycle). Positive when the unloading
    branch lies above the loading branch (displacement lags voltage)."""
    v = jnp.asarray(voltage)
    z = jnp.asarray(disp)
    return -jnp.sum(0.5 * (z[1:] + z[:-1]) * jnp.diff(v))
