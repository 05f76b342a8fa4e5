"""The transient's extrapolation (``StepControl(extrapolate=...)``): the recurrence fit on
sequences with known modes, and the engine's jump against the full 100-cycle run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdea
from jaxdea.engine import extrapolate, step_control
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
    pred, error, _ = extrapolate.predict(ring(x, cycle), jnp.asarray(cycle), jnp.asarray(target))
    jump = np.max(np.abs(x[target] - x[cycle]))
    assert jump > 1e-3  # the jump is not trivial
    assert np.max(np.abs(np.asarray(pred) - x[target])) < tol * jump
    assert float(error) < tol


def test_predict_refuses_growing_or_unstructured_sequences():
    """A growing mode gives no estimate (inf); noise fits no recurrence (large estimate); a
    zero jump costs nothing."""
    x = modes(60, 0.9 * np.exp(0.5j), 1.04)
    _, error, _ = extrapolate.predict(ring(x, 30), jnp.asarray(30), jnp.asarray(55))
    assert not np.isfinite(float(error))
    noise = np.random.default_rng(1).normal(size=(60, 10)) * 1e-3
    _, error, _ = extrapolate.predict(ring(noise, 30), jnp.asarray(30), jnp.asarray(55))
    assert float(error) > 1e-4
    x = modes(60, 0.9 * np.exp(0.5j), 0.8)
    pred, error, _ = extrapolate.predict(ring(x, 30), jnp.asarray(30), jnp.asarray(30))
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
    (measured on 25 000 cells of the paper map's slice with the first landing rule, at the
    averaged cycles with the step proposed mid-cycle: P_out max 5.7e-5, p99 7.8e-6; now the
    jump lands 5 cycles short of them with its cycle end's step), for less than 60 % of the
    early-exit run's steps (45 % with the first rule)."""
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


def test_a_cells_jump_does_not_depend_on_its_pool(models, monkeypatch):
    """Every lane that completed a cycle tries its jump in that round, whatever else its pool
    is doing: 32 cells at one frequency in one 32-lane pool and in 4 lanes give every cell
    the same jump and the same metrics. With the fits 2 at a time, several batches of
    tries run in most of the wide pool's rounds (before, a lane not among the first
    :data:`~jaxdea.engine.extrapolate.TRIES` tried only after its next cycle); in batches
    of a quarter of the pool (:data:`~jaxdea.engine.extrapolate.TRY_BATCHES`, as an
    accelerator's wide pools fit theirs) the same again."""
    monkeypatch.setattr(extrapolate, "TRIES", 2)
    model = models["dcdea_ls"]
    rng = np.random.default_rng(3)
    n = 32
    loads = make_loadings(model, 10 ** rng.uniform(-3, -2, n), 10 ** rng.uniform(-1, 0, n),
                          np.full(n, 120.0), "A")

    def run(w, x, batches):
        monkeypatch.setattr(extrapolate, "TRY_BATCHES", batches)
        return jax.jit(lambda ld: run_protocol(
            model.actuator, ld, cycles=60, average=5, settle=1e-8, require_settled=False,
            control=jaxdea.StepControl(extrapolate=x), lanes=w, pools=(w,), driven=(0,)))(
            loads)

    runs = [run(n, 1e-7, n), run(4, 1e-7, n), run(n, None, n), run(n, 1e-7, 4)]
    assert extrapolate.try_width(n) == n // 4
    # cells that jumped (a jump skips cycles: fewer steps than with the early exit alone)
    assert (np.asarray(runs[0].steps) < np.asarray(runs[2].steps)).sum() > n // 2
    for other in (runs[1], runs[3]):
        for k in ("P_out", "P_in", "amplitude", "cycles_run", "steps"):
            np.testing.assert_allclose(np.asarray(getattr(other, k)),
                                       np.asarray(getattr(runs[0], k)), rtol=1e-12, err_msg=k)


def test_wide_pools_fit_their_tries_in_a_few_batches():
    """The CPU's pools (128 lanes) fit :data:`~jaxdea.engine.extrapolate.TRIES` lanes at a
    time, as before; an accelerator's pool as wide as a chunk fits 1/8 of its lanes at a
    time, not 16 (a round would launch the fit's kernels thousands of times)."""
    assert [extrapolate.try_width(w) for w in (8, 128, 250_000)] == [8, 16, 31_250]


def test_extrapolate_is_checked_and_recorded(models):
    model = models["scdea_ls"]
    with pytest.raises(jaxdea.SweepError, match=r"extrapolate = 2\.0 is outside the allowed "
                                                r"range \(0, 1\)"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0],
                     control=jaxdea.StepControl(extrapolate=2.0))
    ds = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0], cycles=30, average=2,
                      control=jaxdea.StepControl(extrapolate=1e-7))
    assert ds.attrs["extrapolate"] == 1e-7 and (ds.status == 0).all()


@pytest.mark.parametrize("config, payload", [
    ("scdea_ls", jaxdea.Drag(2e-3, linear=0.05, coulomb=0.02)),
    ("dcdea_rr", jaxdea.Drag(3e-3, quadratic=0.5, coulomb=0.01)),
])
def test_extrapolated_payload_laws_match_the_full_run(models, config, payload):
    """The jump with nonlinear payload laws (a smoothed Coulomb drag, whose stiff creep at the
    reversals the step control resolves, and a quadratic drag) on the other configurations:
    the same P_out, P_in and amplitude as every cell's full 60-cycle run to the integration's
    accuracy. The Coulomb drag's 170 Hz cell passes the fit's check and lands off its
    trajectory (P_out 4e-4, amplitude 3.7e-3 off the full run when the jump is kept); the
    cycle after the landing shows it, and the cell goes back (``extrapolate.verify``)."""
    model = models[config]
    freq = np.array([60.0, 110.0, 170.0])
    kw = dict(payload=payload, freq=freq, cycles=60, average=5)
    strict = jaxdea.sweep(model, early_exit=None, **kw)
    jumped = jaxdea.sweep(model, control=jaxdea.StepControl(extrapolate=1e-7), **kw)
    assert (jumped.status.values == 0).all()
    assert (jumped.steady.values == strict.steady.values).all() and strict.steady.sum() >= 2
    for k, tol in (("P_out", 1e-4), ("P_in", 1e-4), ("amplitude", 1e-3)):
        err = np.abs(jumped[k].values / strict[k].values - 1)
        assert err.max() < tol, (k, err)


def test_extrapolated_continuation_matches_the_full_run(models):
    """The continuation protocol (each frequency from the one before's final state): a cell
    that starts near its orbit jumps, or exits early, from its own history, never from its
    predecessor's; the answers are the full 60-cycle runs'."""
    model = models["dcdea_ls"]
    freq = np.linspace(80.0, 160.0, 5)
    kw = dict(mass=5e-3, damping=0.2, freq=freq, cycles=60, average=5,
              protocol="continuation")
    strict = jaxdea.sweep(model, early_exit=None, **kw)
    jumped = jaxdea.sweep(model, control=jaxdea.StepControl(extrapolate=1e-7), **kw)
    assert (jumped.status.values == 0).all()
    assert (jumped.steady.values == strict.steady.values).all() and strict.steady.sum() >= 3
    assert jumped.steps.values.sum() < strict.steps.values.sum()
    for k, tol in (("P_out", 1e-4), ("P_in", 1e-4), ("amplitude", 1e-3)):
        err = np.abs(jumped[k].values / strict[k].values - 1)
        assert err.max() < tol, (k, err)


def test_a_spurious_mode_does_not_jump(models):
    """At this cell of the paper map's slice the fit's own check passed at cycle 41 (estimate
    7e-8) on a recurrence whose spurious mode the 54-cycle sum amplified: the landing was
    4.9e-3 off, P_out 7e-4 and the amplitude 1.6e-2 off the full run. A jump now also needs
    the prediction of the cycle before to agree (``extrapolate.AGREE``)."""
    kw = dict(mass=0.01, damping=2.9470517025518097, freq=[185.0])
    strict = jaxdea.sweep(models["dcdea_ls"], early_exit=None, **kw)
    jumped = jaxdea.sweep(models["dcdea_ls"], control=jaxdea.StepControl(extrapolate=1e-7),
                          **kw)
    assert jumped.steps.values[0] < 0.6 * strict.steps.values[0]  # it jumped
    for k, tol in (("P_out", 1e-5), ("amplitude", 1e-4)):
        err = np.abs(jumped[k].values / strict[k].values - 1)
        assert err.max() < tol, (k, err)


def test_auto_extrapolates_big_jobs_only(models, monkeypatch):
    """``StepControl(extrapolate="auto")``, the default: the tolerance
    :data:`~jaxdea.engine.step_control.EXTRAPOLATE` for a job of at least
    :data:`~jaxdea.engine.step_control.EXTRAPOLATE_FROM` cells (whose compile the jumps
    repay), off for a smaller one, without an early exit and in single precision; a
    tolerance or None stays; any other word is one clear error. A sweep records what it ran
    with, and its answers with and without the jumps agree to the early exit's accuracy."""
    auto = jaxdea.StepControl()
    assert auto.extrapolate == step_control.AUTO
    resolve = step_control.resolve_extrapolate
    big = step_control.EXTRAPOLATE_FROM
    assert resolve(auto, big, 1e-8).extrapolate == step_control.EXTRAPOLATE
    assert resolve(auto, big - 1, 1e-8).extrapolate is None
    assert resolve(auto, big, None).extrapolate is None  # nothing would jump
    assert resolve(auto._replace(precision="single"), 10 * big, 1e-5).extrapolate is None
    for x in (None, 1e-6):
        assert resolve(auto._replace(extrapolate=x), 10 * big, 1e-8).extrapolate == x
    model = models["scdea_ls"]
    with pytest.raises(jaxdea.SweepError, match=r"extrapolate = 'yes' must be a tolerance in "
                                                r"\(0, 1\), None \(off\) or 'auto'"):
        jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=[60.0],
                     control=jaxdea.StepControl(extrapolate="yes"))
    kw = dict(mass=2e-3, damping=0.1, freq=[60.0, 140.0], cycles=60, average=5)
    small = jaxdea.sweep(model, **kw)
    monkeypatch.setattr(step_control, "EXTRAPOLATE_FROM", 2)
    large = jaxdea.sweep(model, **kw)
    assert small.attrs.get("extrapolate") is None  # (a None attribute is not stored)
    assert large.attrs["extrapolate"] == step_control.EXTRAPOLATE
    assert large.steps.values.sum() < small.steps.values.sum()  # it jumped
    for k in ("P_out", "P_in", "amplitude"):
        np.testing.assert_allclose(large[k].values, small[k].values, rtol=1e-5, err_msg=k)
