"""Physics of the shared building blocks: material law, electrostatics, solver, gradients."""

from __future__ import annotations

import math
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxdea
from jaxdea.materials import GentMaxwell, gent_denominator
from jaxdea.solver import ExponentialRK4, LawsonRK4, Linearisation, SemilinearTerm, phi_functions

CONFIGS = Path(__file__).parents[1] / "configs"
LAWS = {
    "dielectric": GentMaxwell(0.47e6, 30.0, 0.21e6, 30.0, 2.0e-3),
    "electrode": GentMaxwell(3.5e6, 20.0, 0.66e6, 20.0, 1.5e-3),
}


@jax.jit
def _dashpot_checks(law: GentMaxwell, l1, xi):
    rate = law.dashpot_rate(l1, xi)
    power = law.dashpot_driving_stress(l1, xi) * rate / xi
    s1, ds1 = jax.value_and_grad(lambda x: law.viscous_stress(l1, x))(xi)
    return power, 2.0 * s1 * ds1 * rate, s1, rate


@settings(max_examples=300, deadline=None)
@given(
    layer=st.sampled_from(sorted(LAWS)),
    l1=st.floats(0.7, 3.0),
    elastic=st.floats(0.5, 3.0),
)
def test_every_dashpot_dissipates(layer, l1, elastic):
    """Paper 000 eq 14: the dashpot's power (driving stress x stretch rate) is >= 0, and at
    fixed total stretch the branch stress relaxes (its magnitude never grows)."""
    law = LAWS[layer]
    xi = l1 / elastic
    if not float(gent_denominator(elastic, 1.0, law.J_B)) > 0.05:
        return  # beyond Gent lock-up the law is undefined (config and solver reject it)
    power, d_s1_sq, s1, rate = (float(v) for v in _dashpot_checks(law, l1, xi))
    assert power >= 0.0
    assert d_s1_sq <= 1e-9 * s1 * s1 * (abs(rate) + 1.0)


def test_relaxed_branch_is_stress_free():
    for law in LAWS.values():
        for l1 in (0.8, 1.0, 1.36, 2.0):
            assert abs(float(law.viscous_stress(l1, l1))) < 1e-6
            assert abs(float(law.dashpot_rate(l1, l1))) < 1e-12


def test_electrostatic_force_is_linear_in_d():
    """Eq 15 electrostatic part: 2 pi a sin(alpha) H_m eps E^2, exactly linear in d
    (0.2154 N at 4.9 kV, d0 = 4 mm; reference/cone_power.md item 7)."""
    mem = jaxdea.load_config(CONFIGS / "scdea_ls.toml").actuator.membrane
    d = jnp.array([1e-3, 2e-3, 4e-3, -4e-3])
    xi_m, xi_el = mem.relaxed_dashpots(d)
    q_full = mem.capacitance(d) * 4.9e3
    f_on = mem.respond(d, q_full, xi_m, xi_el, 4.9e3).force
    f_off = mem.respond(d, jnp.zeros(4), xi_m, xi_el, 0.0).force
    fe = np.asarray(f_on - f_off)
    np.testing.assert_allclose(fe[2], 0.2154, rtol=2e-4)
    np.testing.assert_allclose(fe / np.asarray(d), fe[2] / 4e-3, rtol=1e-12)
    # restoring and odd in d
    assert float(f_off[2]) < 0 and np.isclose(float(f_off[2]), -float(f_off[3]), rtol=1e-14)


def test_rc_time_constant():
    mem = jaxdea.load_config(CONFIGS / "scdea_ls.toml").actuator.membrane
    tau_rc = 1.0 / float(mem.charge_relaxation_rate(4e-3))
    assert 45e-6 < tau_rc < 52e-6  # ~49 us (paper 000 eq 3-5 with the reference cone)


# ---------------------------------------------------------------- solver --------------------
class _Scalar(Linearisation):
    kappa: jax.Array
    target: jax.Array

    @property
    def fixed_point(self):
        return jnp.stack([self.target, 0.0])

    def apply(self, z):
        return jnp.stack([-self.kappa * z[0], 0.0 * z[1]])

    def flow(self, h, z):
        return jnp.stack([jnp.exp(-self.kappa * h) * z[0], z[1]])

    def phi_k(self, k, h, z):
        pk = phi_functions(-self.kappa * h, k)[k]
        return jnp.stack([pk * z[0], z[1] / math.factorial(k)])


def _test_problem(kappa=2e4):
    """Stiff RC-like charge q driven by a slowly varying 'capacitance' c(x), x' = omega:
    q' = kappa (c(x) - q) with c(x) = 1 + 0.3 sin(x). Exact slow manifold is smooth."""

    def vf(t, y, args):
        c = 1.0 + 0.3 * jnp.sin(y[1])
        return jnp.stack([kappa * (c - y[0]), 50.0 + 0.0 * y[1]])

    def lin(t, y, args):
        return _Scalar(kappa=jnp.asarray(kappa), target=1.0 + 0.3 * jnp.sin(y[1]))

    return SemilinearTerm(vf, lin)


def _reference(term, y0, t1):
    """``y(t1)`` by an implicit solver (Kvaerno5) at rtol 1e-12."""
    return diffrax.diffeqsolve(
        diffrax.ODETerm(term.vector_field), diffrax.Kvaerno5(), 0.0, t1, 1e-6, y0,
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-14), max_steps=100000,
    ).ys[-1]


def _solve(term, y0, t1, n, solver=LawsonRK4()):
    sol = diffrax.diffeqsolve(term, solver, 0.0, t1, t1 / n, y0,
                              stepsize_controller=diffrax.ConstantStepSize(), max_steps=n + 1)
    return sol.ys[-1]


SOLVERS = pytest.mark.parametrize("solver", [LawsonRK4(), ExponentialRK4()],
                                  ids=["lawson", "exponential"])


@SOLVERS
def test_lawson_steady_charge_is_a_fixed_point(solver):
    """A resting capacitor charged to C*Phi stays exactly there, whatever the step."""
    term = _test_problem()

    def vf(t, y, args):
        return jnp.stack([2e4 * (1.0 - y[0]), 0.0 * y[1]])

    flat = SemilinearTerm(vf, lambda t, y, a: _Scalar(jnp.asarray(2e4), jnp.asarray(1.0)))
    y = _solve(flat, jnp.array([1.0, 0.0]), 0.1, 7, solver)  # 14 ms steps = 290 RC constants
    assert float(jnp.abs(y[0] - 1.0)) == 0.0
    del term


@SOLVERS
def test_lawson_is_stable_and_fourth_order_beyond_the_rc_limit(solver):
    """Steps of 1-40 RC constants (explicit RK4 diverges above ~2.8): stable throughout,
    at least 2nd order while kappa h >> 1 (stiff order reduction, the adaptive controller
    sees it through the embedded estimate) and 4th order once kappa h ~ 1."""
    term = _test_problem()
    y0 = jnp.array([0.0, 0.0])
    ref = _reference(term, y0, 0.2)
    ns = (100, 200, 400, 800, 1600, 3200)  # kappa h = 40 ... 1.25
    errs = np.array([float(jnp.abs(_solve(term, y0, 0.2, n, solver)[0] - ref[0])) for n in ns])
    assert errs[0] < 0.2  # kappa h = 40: bounded, no blow-up
    orders = np.log2(errs[:-1] / errs[1:])
    assert np.all(orders > 2.0), (errs, orders)
    assert orders[-1] > 3.7, (errs, orders)


def test_exponential_rk4_is_accurate_where_lawson_is_not():
    """On the stiff test problem the remainder (the slow manifold's drift) is not small, so
    Lawson's error carries powers of kappa; Krogstad's exponential RK4 integrates it against
    the exact kernel: at kappa h = 40 ... 5 (100 ... 800 steps over 0.2 s, 1 / kappa =
    50 us) it is at least 100x more accurate (measured 3e5x ... 2.5e5x), and within 1e-6."""
    term = _test_problem()
    y0 = jnp.array([0.0, 0.0])
    ref = _reference(term, y0, 0.2)
    for n in (100, 200, 400, 800):
        law = float(jnp.abs(_solve(term, y0, 0.2, n)[0] - ref[0]))
        exp = float(jnp.abs(_solve(term, y0, 0.2, n, ExponentialRK4())[0] - ref[0]))
        assert exp * 100 < law and exp < 1e-6, (n, law, exp)


def test_phi_functions_match_their_definition():
    """phi_k(a) = sum_j a^j / (j + k)! for a <= 0, against exact rational arithmetic at
    points on both sides of the series/recurrence switch (|a| = 0.1), to 1e-14."""
    from fractions import Fraction

    def exact(a, k, terms=60):
        a = Fraction(a)
        return float(sum(a ** j / math.factorial(j + k) for j in range(terms)))

    pts = [0.0, -1e-9, -0.05, -0.0999, -0.1001, -0.3, -1.0, -4.0, -20.0]
    got = phi_functions(jnp.asarray(pts), 3)
    for k in range(4):
        for a, g in zip(pts, np.asarray(got[k])):
            want = math.exp(a) if k == 0 else exact(a, k, 200 if a < -5 else 60)
            assert abs(g - want) <= 1e-14 * max(1.0, abs(want)), (k, a, g, want)


# ------------------------------------------------------------- protocol -----------------------
@pytest.fixture(scope="module")
def ls_model():
    return jaxdea.load_config(CONFIGS / "dcdea_ls.toml")


def test_published_two_mode_response(ls_model):
    """Paper 000 Sec III.B / issue 2 criterion: DCDEA-LS drive A, M = 2 g, c = 0.1 N s/m,
    100 cycles, mean of last 5: local P_out max 6.7 +- 0.4 mW in 66-74 Hz and the global max
    19.1 +- 0.6 mW in 126-133 Hz over 40-200 Hz. A 2-Hz grid over the band plus 0.2-Hz grids
    over both peaks (one call)."""
    f = np.unique(np.round(np.concatenate([
        np.arange(40, 200.1, 2.0), np.arange(64, 76.01, 0.2), np.arange(125, 134.01, 0.2),
    ]), 6))
    ds = jaxdea.sweep(ls_model, mass=2e-3, damping=0.1, freq=f, drive="A")
    assert np.all(ds.status.values == 0)
    p = ds.P_out.values * 1e3
    glob = int(np.argmax(p))
    assert 126 <= f[glob] <= 133 and abs(p[glob] - 19.1) <= 0.6, (f[glob], p[glob])
    band = (f >= 60) & (f <= 80)
    loc = int(np.argmax(np.where(band, p, -1)))
    assert 66 <= f[loc] <= 74 and abs(p[loc] - 6.7) <= 0.4, (f[loc], p[loc])
    assert p[loc] > p[max(loc - 5, 0)] and p[loc] > p[min(loc + 5, f.size - 1)]
    pin, eff = ds.P_in.values, ds.efficiency.values
    assert np.all(pin >= ds.P_out.values) and np.all(ds.P_out.values >= 0)
    assert np.all((eff >= 0) & (eff <= 1))
    assert np.all(ds.P_in_signed.values <= pin * (1 + 1e-12))


def test_trajectory_path_agrees_with_protocol(ls_model):
    """The diffeqsolve trajectory (fixed steps, 400 per cycle) and the adaptive protocol give
    the same P_out over the last 5 of 20 cycles."""
    tr = jaxdea.simulate(ls_model, mass=2e-3, damping=0.1, freq=129.0, cycles=20,
                         points_per_cycle=400)
    t = tr.t.values
    w = t >= 15 / 129.0 - 1e-12
    v = tr.payload_velocity.values[w]
    p_traj = 0.1 * np.trapezoid(v * v, t[w]) / (5 / 129.0)
    ds = jaxdea.sweep(ls_model, mass=2e-3, damping=0.1, freq=[129.0], cycles=20, average=5)
    np.testing.assert_allclose(p_traj, float(ds.P_out[0]), rtol=2e-3)
    x = tr.payload_position.values[w]
    np.testing.assert_allclose(0.5 * (x.max() - x.min()), float(ds.amplitude[0]), rtol=2e-3)


def test_gradient_matches_finite_differences(ls_model):
    """Forward-mode derivative of P_out and P_in w.r.t. the dielectric's mu_A and the
    electrode resistance through the whole protocol matches central differences."""
    load = jaxdea.make_loadings(ls_model, 2e-3, 0.1, np.array([90.0]), "A")
    control = jaxdea.StepControl(rtol=1e-9)

    @eqx.filter_jit
    def metrics(scale):
        act = eqx.tree_at(
            lambda a: (a.membrane.dielectric.mu_A, a.membrane.electrode_resistance),
            ls_model.actuator,
            (ls_model.actuator.membrane.dielectric.mu_A * scale[0],
             ls_model.actuator.membrane.electrode_resistance * scale[1]),
        )
        r = jaxdea.run_protocol(act, load, cycles=6, average=2, control=control)
        return jnp.stack([r.P_out[0], r.P_in[0]])

    one = jnp.ones(2)
    jac = jax.jacfwd(metrics)(one)
    eps = 1e-4
    for k in range(2):
        e = jnp.zeros(2).at[k].set(eps)
        fd = (metrics(one + e) - metrics(one - e)) / (2 * eps)
        np.testing.assert_allclose(np.asarray(jac[:, k]), np.asarray(fd), rtol=2e-3, atol=1e-9)
    assert np.all(np.abs(np.asarray(jac)) > 0)


def _returned_charge_exact(q0, i0, q1, i1, h, kappa, q_inf):
    """Reference for ``returned_charge``: the same interpolant's zeros by scipy's brentq on a
    dense sign scan, and the negative parts from its antiderivative."""
    from scipy.optimize import brentq

    z0 = q0 - q_inf
    dh = np.exp(-kappa * h)
    dr0 = i0 + kappa * z0
    x1, v1 = q1 - q_inf - z0 * dh, i1 + kappa * z0 * dh
    a = (3.0 * x1 / h - 2.0 * dr0 - v1) / h
    b = (dr0 + v1 - 2.0 * x1 / h) / (h * h)

    def i(s):
        return -kappa * z0 * np.exp(-kappa * s) + dr0 + s * (2 * a + 3 * b * s)

    def q(s):
        return z0 * (np.exp(-kappa * s) - 1.0) + s * (dr0 + s * (a + b * s))

    s = np.linspace(0.0, h, 20001)
    v = i(s)
    cuts = [brentq(i, s[k], s[k + 1], xtol=1e-30, rtol=1e-15)
            for k in np.flatnonzero(np.sign(v[:-1]) * np.sign(v[1:]) < 0)]
    ends = [0.0, *cuts, h]
    back = sum(q(e) - q(s0) for s0, e in zip(ends[:-1], ends[1:]) if i(0.5 * (s0 + e)) < 0)
    return back, len(cuts), np.abs(v).mean() * h


def test_returned_charge_is_exact_and_smooth():
    """The charge pushed back into the source over a step (the returned part of P_in) is the
    interpolant's exact negative part wherever its current changes sign once, with RC
    transients from 1e-3 to 10 time constants per step; its derivative is continuous where the
    zero passes through the step's end (central differences across that point agree with
    jax.grad on both sides)."""
    from jaxdea.models.cone import returned_charge

    rng = np.random.default_rng(1)
    n = 400
    h = 10 ** rng.uniform(-7, -4, n)
    kappa = 10 ** rng.uniform(4, 5, n)
    h = np.minimum(h, 10.0 / kappa)
    q_inf = rng.normal(size=n) * 1e-6
    q0 = q_inf + rng.normal(size=n) * 1e-9
    i0, i1 = rng.normal(size=n) * 1e-4, rng.normal(size=n) * 1e-4
    q1 = q0 + 0.5 * (i0 + i1) * h * (1 + 0.1 * rng.normal(size=n))
    got = np.asarray(jax.vmap(returned_charge)(q0, i0, q1, i1, h, kappa, q_inf))
    counted = 0
    for k in range(n):
        exact, zeros, scale = _returned_charge_exact(q0[k], i0[k], q1[k], i1[k], h[k], kappa[k],
                                                     q_inf[k])
        if zeros <= 1:  # no dip below zero and back inside the step
            counted += 1
            assert abs(got[k] - exact) <= 1e-10 * scale, (k, got[k], exact, zeros)
    assert counted > 0.9 * n
    assert np.sum(np.sign(i0) != np.sign(i1)) > 0.3 * n  # most of them cross

    # the zero leaves through the end of the step as i1 passes 0: value and slope continuous
    q0, i0, h, kappa, q_inf = 1e-6, -2e-4, 2e-5, 2e4, 1e-6 + 3e-9

    def f(i1):
        return returned_charge(q0, i0, q0 + 0.5 * (i0 + i1) * h, i1, h, kappa, q_inf)

    assert _returned_charge_exact(q0, i0, q0 + 0.5 * (i0 + 1e-12) * h, 1e-12, h, kappa,
                                  q_inf)[1] == 1  # a zero inside the step on this side only
    g = jax.grad(f)
    below, above = float(g(-1e-12)), float(g(1e-12))
    assert np.isclose(below, above, rtol=1e-6), (below, above)
    fd = (float(f(1e-9)) - float(f(-1e-9))) / 2e-9
    assert np.isclose(fd, below, rtol=1e-6), (fd, below)
