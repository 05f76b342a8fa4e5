"""Issue 5, problem (a): recovery of known mass-cone spring/dashpot parameters (paper 002,
``jaxdea.huang2020()``) from synthetic data made by jaxdea itself under an eq-25 multi-sine,
with 1 % noise, by L-BFGS from starts off by a factor of 3.

Size (to keep the test near a minute): a time-scaled eq-25 drive, the paper's amplitudes
6-8 kV with the frequencies x5 (1-5 Hz instead of 0.2-1 Hz: one 2.28-s period instead of
11.4 s), 115 samples, 228 fixed Kvaerno5 steps (the same discretisation generates and fits
the data, so it is not a source of error). Gradients are reverse mode (``jac="rev"``):
diffrax's checkpointed adjoint is a ``custom_vjp``, which forward mode cannot go through, so
``calibrate``'s default ``jac="fwd"`` and its curvature (``jacfwd``) do not apply here; the
Gauss-Newton curvature is built below from central differences of the residual vector (the
fixed-step solution is smooth in the parameters).

The load ``P`` of the cone is computed once when the model is built and is not recomputed
when material parameters change. That is consistent here: ``P`` only depends on the
equilibrium spring (``mu0``, ``J0``: at rest the dashpots are relaxed and the other units
carry no stress), which is not fitted, and data and fit use the same model build.

Identifiability (what the data can say in a 2.28-s window): unit 1 (mu 5.3 MPa, tau 0.01 s)
acts as a dashpot of viscosity ~ mu tau at drive time scales >> 0.01 s, so mainly the
product mu[0] tau[0] is fixed; units 3 and 4 (tau 9.8 s and 8485 s) barely relax in the
window, so mainly the sum of their moduli is fixed, and tau[3] not at all. The test therefore
asserts, per parameter, either recovery within 5 % or that the curvature along it is flat,
i.e. its Gauss-Newton 1-sigma (1 % noise) is above 5 % (not identifiable to the required
accuracy), and that the error is consistent with that sigma; it prints which is which. It
also asserts that the identified combinations, mu[0] tau[0] and mu[2] + mu[3], come back within
5 %, and that e_rms (paper 002 eq 26) is below 2 %.
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.calibration import TimeSeries, calibrate, get_params, set_params, transient_predictor
from jaxdea.signals import MultiSine

A = [6000.0, 6500.0, 7000.0, 7500.0, 8000.0]  # paper 002 eq 25 amplitudes (V)
F = [1.0, 2.0, 3.0, 4.0, 5.0]  # paper 002's 0.2-1 Hz, x5 (Hz)
N_SAMPLES = 115
FIXED_STEPS = 228
FIT = ["material.mu[0]", "material.tau[0]", "material.mu[2]", "material.tau[2]",
       "material.mu[3]", "material.tau[3]"]


def problem_a(seed: int = 0, noise: float = 0.01):
    """(start model, data, truth, bounds, predict, signal) of problem (a)."""
    true = jaxdea.huang2020()
    sig = MultiSine(jnp.asarray(A), jnp.asarray(F))
    ts = np.linspace(0.0, float(sig.period), N_SAMPLES)
    volts = np.asarray(jax.vmap(sig)(jnp.asarray(ts)))
    predict = transient_predictor(sig, fixed_steps=FIXED_STEPS)
    shape = TimeSeries(t=ts, voltage=volts, displacement=0 * ts)
    clean = np.asarray(jax.jit(lambda m: predict(m, shape)["displacement"])(true))
    rng = np.random.default_rng(seed)
    data = TimeSeries(t=ts, voltage=volts, displacement=clean + noise * np.ptp(clean)
                      * rng.standard_normal(ts.size))
    truth = get_params(true, FIT)
    start = set_params(true, {k: v * (3.0 if i % 2 == 0 else 1 / 3)
                              for i, (k, v) in enumerate(truth.items())})
    bounds = {k: (v / 10, v * 10) for k, v in truth.items()}
    return start, data, truth, bounds, predict, sig


def gauss_newton_sigma(res, h: float = 1e-4):
    """Relative 1-sigma of each fitted parameter (log space) from the Gauss-Newton curvature,
    with the residual Jacobian in u = log(theta) by central differences."""
    obj = res.objective
    resid_u = jax.jit(obj.residual_u)
    u0 = np.log([res.params[p.name] for p in obj.params])
    r0 = np.asarray(resid_u(jnp.asarray(u0)))
    J = np.empty((r0.size, u0.size))
    for i in range(u0.size):
        e = np.zeros_like(u0)
        e[i] = h
        J[:, i] = (np.asarray(resid_u(jnp.asarray(u0 + e)))
                   - np.asarray(resid_u(jnp.asarray(u0 - e)))) / (2 * h)
    H = 2.0 * J.T @ J  # Gauss-Newton Hessian of the loss in u
    s2 = float(r0 @ r0) / max(r0.size - u0.size, 1)
    cov_u = s2 * np.linalg.pinv(0.5 * H, rcond=1e-14, hermitian=True)
    return np.sqrt(np.clip(np.diag(cov_u), 0, None)), H, resid_u


@pytest.fixture(scope="module")
def fitted():
    start, data, truth, bounds, predict, _ = problem_a()
    t0 = time.perf_counter()
    res = calibrate(start, data, FIT, bounds=bounds, method="lbfgs", predict=predict,
                    jac="rev", curvature=False, tol=1e-8)
    return res, truth, time.perf_counter() - t0


def test_mass_cone_recovery_lbfgs(fitted):
    res, truth, wall = fitted
    sigma, H, _ = gauss_newton_sigma(res)
    evals = np.linalg.eigvalsh(H)
    print(f"\nL-BFGS: {res.n_evals} evaluations, {wall:.1f} s, loss {res.loss:.4e}, "
          f"e_rms {res.e_rms:.3f} %, e_m {res.e_m:.3f} %")
    print("Gauss-Newton curvature eigenvalues (log space): "
          + ", ".join(f"{e:.2e}" for e in evals))
    identified, flat = [], []
    for (name, v), s in zip(truth.items(), sigma):
        err = res.params[name] / v - 1
        kind = "recovered" if abs(err) < 0.05 else "flat (not identified to 5 %)"
        print(f"  {name:16s} true {v:.5g} fitted {res.params[name]:.5g} error {100 * err:+7.2f} %"
              f"  1-sigma {100 * s:.3g} %  -> {kind}")
        if abs(err) < 0.05:
            identified.append(name)
        else:
            # the data cannot identify it: its 1-sigma exceeds the 5 % target and the error
            # it ends with is within what that curvature allows
            assert s > 0.05, f"{name}: error {err:+.1%} but 1-sigma only {s:.1%}"
            assert abs(math.log1p(err)) < 4 * s, f"{name}: error {err:+.1%} > 4 sigma"
            flat.append(name)
    print(f"recovered within 5 %: {identified}; flat (data do not identify): {flat}")
    # what the data do identify: the dashpot-like unit 1's viscosity ~ mu[0] tau[0], and the
    # summed modulus of the units that hardly relax in the window, mu[2] + mu[3]
    P = res.params
    visc = P[FIT[0]] * P[FIT[1]] / (truth[FIT[0]] * truth[FIT[1]]) - 1
    stiff = (P[FIT[2]] + P[FIT[4]]) / (truth[FIT[2]] + truth[FIT[4]]) - 1
    print(f"identified combinations: mu[0] tau[0] error {100 * visc:+.2f} %, "
          f"mu[2] + mu[3] error {100 * stiff:+.2f} %")
    assert abs(visc) < 0.05 and abs(stiff) < 0.05
    assert res.e_rms < 2.0
    assert identified, "no parameter recovered"


def test_mass_cone_gradient_matches_finite_differences(fitted):
    """The reverse-mode gradient the fit uses matches central differences of its loss."""
    res, _, _ = fitted
    obj = res.objective
    z = np.array([p.z_of_u(math.log(res.params[p.name])) for p in obj.params])
    rng = np.random.default_rng(3)
    z = z + 0.3 * rng.standard_normal(z.size)  # off the optimum: a non-trivial gradient
    f, g = obj.value_and_grad(z, "rev")
    loss = obj.fn("resid_z")
    d = rng.standard_normal(z.size)
    d /= np.linalg.norm(d)
    h = 1e-5
    fp = float(np.sum(np.asarray(loss(jnp.asarray(z + h * d))) ** 2))
    fm = float(np.sum(np.asarray(loss(jnp.asarray(z - h * d))) ** 2))
    fd = (fp - fm) / (2 * h)
    print(f"\ndirectional derivative: reverse mode {g @ d:.8e}, central FD {fd:.8e}")
    assert g @ d == pytest.approx(fd, rel=1e-4, abs=1e-6 * f)
