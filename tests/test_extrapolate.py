"""The transient's extrapolation (``StepControl(extrapolate=...)``): the recurrence fit on
sequences with known modes, and the engine's jump against the full 100-cycle run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.engine import extrapolate
from jaxdea.engine.lanes import run_protocol
from jaxdea.studies.loadings import make_loadings

H = extrapolate.HISTORY


def ring(x: np.ndarray, cycle: int) -> jnp.ndarray:
    """The engine's history ring holding the states after cycles ``cycle - H + 1 .. cycle``
    (``x[j]`` = state after ``j`` cycles)."""
    hist = np.zeros((H, x.shape[1]))
    for j in range(cycle - H + 1, cycle + 1):
        hist[j % H] = x[j]
    return jnp.asarray(hist)


def modes(n_cycles: int, lam: complex, mu: complex, seed: int = 0) -> np.ndarray:
    """Cycle-start states of a transient with a complex pair ``lam`` and a mode ``mu`` (a
    real one, or another pair) decaying onto a fixed point, 10 components."""
    rng = np.random.default_rng(seed)
    x_star = rng.normal(size=10)
    v, w = (rng.normal(size=10) + 1j * rng.normal(size=10) for _ in range(2))
    if np.isreal(mu):
        w = w.real
    j = np.arange(n_cycles)[:, None]
    return x_star + np.real(0.3 * lam ** j * v) + np.real(0.2 * mu ** j * w)


@pytest.mark.parametrize("mu,tol", [(0.8 * np.exp(2.1j), 1e-11), (0.85, 1e-7)])
def test_predict_is_exact_on_a_linear_recurrence(mu, tol):
    """Two complex pairs obey an order-4 recurrence, the fit's: the state 62 cycles on is
    predicted to rounding. A pair and a real mode obey an order-3 one, which the order-4
    fit contains (its normal equations are then singular but for the ridge: 1e-8)."""
    x = modes(100, 0.93 * np.exp(0.7j), mu)
    cycle, target = 33, 95
    pred, error = extrapolate.predict(ring(x, cycle), jnp.asarray(cycle), jnp.asarray(target))
    jump = np.max(np.abs(x[target] - x[cycle]))
    assert jump > 1e-3  # the jump is not trivial
    assert np.max(np.abs(np.asarray(pred) - x[target])) < tol * jump
    assert float(error) < tol


def test_predict_refuses_growing_or_unstructured_sequences():
    """A growing mode gives no estimate (inf); noise fits no recurrence (large estimate); a
    zero jump costs nothing."""
    x = modes(60, 0.9 * np.exp(0.5j), 1.04)
    _, error = extrapolate.predict(ring(x, 30), jnp.asarray(30), jnp.asarray(55))
    assert not np.isfinite(float(error))
    noise = np.random.default_rng(1).normal(size=(60, 10)) * 1e-3
    _, error = extrapolate.predict(ring(noise, 30), jnp.asarray(30), jnp.asarray(55))
    assert float(error) > 1e-4
    x = modes(60, 0.9 * np.exp(0.5j), 0.8)
    pred, error = extrapolate.predict(ring(x, 30), jnp.asarray(30), jnp.asarray(30))
    assert np.array_equal(np.asarray(pred), x[30]) and float(error) == 0.0


def test_power_and_sum_by_doubling():
    a = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)) * 0.4)
    for n in (0, 1, 5, 64, 1023):
        power, total = extrapolate._power_and_sum(a, jnp.asarray(n))
        ref = np.eye(4)
        acc = np.zeros((4, 4))
        for _ in range(n):
            ref = ref @ np.asarray(a)
            acc += ref
        assert np.allclose(power, ref, rtol=1e-9, atol=1e-14)
        assert np.allclose(total, acc, rtol=1e-9, atol=1e-14)


def test_extrapolated_runs_match_the_full_run_in_fewer_steps(models):
    """DCDEA-LS, 24 cells at 60-200 Hz (where cells run the most cycles): with the jump, P_out
    and P_in agree with every cell's full 100-cycle run to the integration's own accuracy
    (measured on 25 000 cells of the paper map's slice: P_out max 5.7e-5, p99 7.8e-6), for
    less than 60 % of the early-exit run's steps (measured 45 %)."""
    model = models["dcdea_ls"]
    rng = np.random.default_rng(0)
    n = 24
    loads = make_loadings(model, 10 ** rng.uniform(-4, -2, n), 10 ** rng.uniform(-1, 1, n),
                          rng.uniform(60.0, 200.0, n), "A")
    kw = dict(cycles=100, average=5, lanes=n, pools=(n, 8), driven=(0,))
    strict = jax.jit(lambda ld: run_protocol(model.actuator, ld, **kw))(loads)
    early, jumped = (jax.jit(lambda ld, c=c: run_protocol(
        model.actuator, ld, settle=1e-8, require_settled=False, control=c, **kw))(loads)
        for c in (jaxdea.StepControl(), jaxdea.StepControl(extrapolate=1e-7)))
    assert (np.asarray(jumped.status) == 0).all()
    for k, tol in (("P_out", 1e-4), ("P_in", 1e-4), ("v_rms", 1e-4), ("amplitude", 1e-3)):
        err = np.abs(np.asarray(getattr(jumped, k)) / np.asarray(getattr(strict, k)) - 1)
        assert err.max() < tol, (k, err.max())
    assert np.sum(jumped.steps) < 0.6 * np.sum(early.steps)


def test_extrapolate_is_checked_and_recorded(models):
    model = models["scdea_ls"]
    with pytest.raises(jaxdea.SweepError, match=r"extrapolate = 2\.0 is outside the allowed "
                                                r"range \(0, 1\)"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0],
                     control=jaxdea.StepControl(extrapolate=2.0))
    ds = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0], cycles=30, average=2,
                      control=jaxdea.StepControl(extrapolate=1e-7))
    assert ds.attrs["extrapolate"] == 1e-7 and (ds.status == 0).all()
