"""Drives of the viscoelastic models: eq-25 multi-sine, VP1-VP4, plain sine (jaxdea.signals)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdea.signals import VOLTAGE_PATTERNS, MultiSine, Sine, voltage_pattern
from viscoelastic_reference import multisine


def test_multisine_is_eq25():
    a = [6000.0, 6500.0, 7000.0, 7500.0, 8000.0]
    f = [0.2, 0.4, 0.6, 0.8, 1.0]
    sig = MultiSine(jnp.asarray(a), jnp.asarray(f))
    assert float(sig.period) == pytest.approx(sum(1 / x for x in f))
    ts = np.linspace(0.0, 3 * float(sig.period), 997)
    got = np.asarray(jax.jit(jax.vmap(sig))(jnp.asarray(ts)))
    want = np.array([multisine(t, a, f) for t in ts])
    assert np.max(np.abs(got - want)) < 1e-8
    assert got.min() >= -1e-9 and got.max() == pytest.approx(8000.0, rel=2e-3)
    # each segment is one half-sine hump of its own amplitude, peaking mid-segment
    starts = np.concatenate([[0.0], np.cumsum(1 / np.asarray(f))[:-1]])
    for ai, fi, s in zip(a, f, starts):
        assert float(sig(s + 0.5 / fi)) == pytest.approx(ai, rel=1e-12)
    # kinks = segment joints
    k = np.asarray(sig.kink_times(1))
    assert np.allclose(k[:6], [0.0, 5.0, 7.5, 9.1666666667, 10.4166666667, 11.4166666667])


def test_multisine_any_number_of_segments_and_vmap():
    sig = MultiSine(jnp.asarray([1.0, 2.0]), jnp.asarray([1.0, 0.5]))
    assert float(sig(0.5)) == pytest.approx(1.0)
    assert float(sig(2.0)) == pytest.approx(2.0)  # second segment [1, 3): peak at 2
    amps = jnp.asarray([[1.0], [3.0]])
    out = jax.vmap(lambda a: MultiSine(a, jnp.asarray([2.0]))(0.25))(amps)
    assert np.allclose(np.asarray(out), [1.0, 3.0])


def test_multisine_bad_inputs():
    with pytest.raises(ValueError, match="a_i or f_i missing"):
        MultiSine(jnp.asarray([1.0, 2.0]), jnp.asarray([1.0]))
    with pytest.raises(ValueError, match="a_i or f_i missing"):
        MultiSine(jnp.asarray([1.0]), jnp.asarray([1.0, 2.0]))
    with pytest.raises(ValueError, match="1-D amplitudes a_i and frequencies f_i"):
        MultiSine(jnp.asarray([]), jnp.asarray([]))
    with pytest.raises(ValueError, match=r"f_i must be finite and > 0"):
        MultiSine(jnp.asarray([1.0]), jnp.asarray([0.0]))


def _extrema(v):
    d = np.diff(v)
    maxima = [v[i] for i in range(1, len(v) - 1) if d[i - 1] > 0 and d[i] < 0]
    minima = [v[i] for i in range(1, len(v) - 1) if d[i - 1] < 0 and d[i] > 0]
    return maxima, minima


def test_triangular_patterns():
    peak, period = 4500.0, 10.0
    ts = np.linspace(0.0, period, 4001)
    vals = {}
    for name in VOLTAGE_PATTERNS:
        sig = voltage_pattern(name, peak, period)
        v = np.asarray(jax.vmap(sig)(jnp.asarray(ts)))
        vals[name] = v
        assert v[0] == 0.0 and v[-1] == pytest.approx(0.0, abs=1e-9)
        assert v.max() == pytest.approx(peak) and v.min() >= 0.0
        slope = np.abs(np.diff(v)) / np.diff(ts)
        # constant |dV/dt| except in the samples that straddle a corner
        assert np.median(slope) == pytest.approx(np.max(slope), rel=1e-6)
        assert float(sig(3.3 + 2 * period)) == pytest.approx(float(sig(3.3)))
    mx, mn = _extrema(vals["vp1"])
    assert len(mx) == 1 and vals["vp1"][2000] == pytest.approx(peak)
    mx, _ = _extrema(vals["vp2"])
    assert len(mx) == 3 and np.all(np.diff(mx) > 0)  # three increasing maxima
    _, mn = _extrema(vals["vp3"])
    mn = mn + [0.0]  # the third minimum is the return to zero
    assert len(mn) == 3 and np.all(np.diff(mn) < 0)  # three decreasing minima
    mx, _ = _extrema(vals["vp4"])
    k = int(np.argmax(mx))
    assert 0 < k < len(mx) - 1 and np.all(np.diff(mx[:k + 1]) > 0) and np.all(
        np.diff(mx[k:]) < 0)
    with pytest.raises(ValueError, match="unknown voltage pattern"):
        voltage_pattern("vp5", peak, period)
    with pytest.raises(ValueError, match="period must be > 0"):
        voltage_pattern("vp1", peak, 0.0)


def test_patterns_are_jit_vmap_and_grad_friendly():
    f = jax.jit(jax.vmap(lambda p: voltage_pattern("vp2", p, 10.0)(2.0)))
    out = np.asarray(f(jnp.asarray([1000.0, 2000.0])))
    assert out[1] == pytest.approx(2 * out[0])
    d = jax.grad(lambda t: voltage_pattern("vp1", 4500.0, 10.0)(t))(2.0)
    assert float(d) == pytest.approx(900.0)  # 4.5 kV in 5 s


def test_sine():
    s = Sine(amplitude=2.0, frequency=0.5, offset=1.0)
    assert float(s(0.5)) == pytest.approx(1.0 + 2.0 * math.sin(0.5 * math.pi))
    out = jax.vmap(lambda f: Sine(1.0, f)(0.25))(jnp.asarray([1.0, 2.0]))
    assert np.allclose(np.asarray(out), [1.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="frequency must be > 0"):
        Sine(1.0, -1.0)
