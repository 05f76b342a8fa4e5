"""The peak search of the design study on a known P(f; theta), without the ODE: a narrow
resonance between grid points is found, P_max lands on the root of dP/df, and the
envelope-theorem gradient equals central differences of the search's own P_max."""

import numpy as np
import pytest

from jaxdea.engine.sensitivity import SteadyResult
from jaxdea.studies import design
from jaxdea.studies.peak_search import hills, next_frequencies, stationary_point

BAND = (20.0, 200.0)


def lorentz(f, f0, a, w):
    x = 2 * (f - f0) / w
    return a / (1 + x**2), -a * 2 * x * (2 / w) / (1 + x**2) ** 2  # P, dP/df


def power(f, theta):
    """A broad hill at 70 Hz and a narrow (3 Hz) resonance at 129.5 (1 + theta0) Hz with
    height 19.5 (1 + theta1): P, dP/dtheta0, dP/dtheta1, dP/df (the paper's DCDEA-LS at
    c = 0.1 N s/m has this shape, in mW)."""
    p1, g1 = lorentz(f, 70.3, 6.7, 8.0)
    f0, a = 129.5 * (1 + theta[0]), 19.5 * (1 + theta[1])
    p2, g2 = lorentz(f, f0, a, 3.0)
    return p1 + p2, -g2 * 129.5, p2 / a * 19.5, g1 + g2


@pytest.fixture
def fake_solver(monkeypatch):
    calls = []

    def solve(build, theta, f, state, settings, full_jac, sub_free, devices=None):
        k, g = f.shape
        p, d0, d1, df = (np.stack(x) for x in zip(*[power(f[i], theta[i]) for i in range(k)]))
        values = np.stack([p, 2 * p, np.full_like(p, 0.5), np.full_like(p, 1e-3)], -1)
        jac = np.zeros((k, g, 4, theta.shape[1] if full_jac else 1))
        jac[..., 0, -1] = df
        if full_jac:
            jac[..., 0, 0], jac[..., 0, 1] = d0, d1
        calls.append(f.copy())
        return SteadyResult(values=values, jac=jac, status=np.zeros((k, g), int),
                            state={"x": np.zeros((k, g, 2))}, residual=np.zeros((k, g)))

    monkeypatch.setattr(design, "_solve_grid", solve)
    return calls


def test_a_narrow_resonance_between_grid_points_is_found(fake_solver):
    theta = np.array([[0.0, 0.0, 0.0]])  # theta0, theta1, frequency shift
    r = design.peak_designs(None, theta, BAND, grid=8)
    # the coarse grid (25.7 Hz steps) has its best sample on the broad hill (6.5 at 71.4 Hz)
    assert np.argmax(power(fake_solver[0][0], theta[0])[0]) == 2
    fine = np.linspace(129.0, 130.0, 200001)
    best = np.argmax(power(fine, theta[0])[0])
    assert abs(r["f"][0] - fine[best]) < 1e-4
    assert abs(r["P_max"][0] - power(fine, theta[0])[0][best]) < 1e-6 * r["P_max"][0]
    assert abs(power(r["f"][0], theta[0])[3]) < 1e-3  # dP/df = 0 there
    assert r["levels"] <= 7
    assert np.allclose(r["metrics"][0], [r["P_max"][0], 2 * r["P_max"][0], 0.5, 1e-3])


def test_pmax_gradient_equals_central_differences_of_the_search(fake_solver):
    theta = np.array([0.01, 0.02, 0.0])
    h = 1e-6
    designs = np.array([theta, theta + [h, 0, 0], theta - [h, 0, 0],
                        theta + [0, h, 0], theta - [0, h, 0]])
    r = design.peak_designs(None, designs, BAND, grid=8)
    fd = [(r["P_max"][1] - r["P_max"][2]) / (2 * h), (r["P_max"][3] - r["P_max"][4]) / (2 * h)]
    # exact: dP_max/dtheta0 = 0 (moving the resonance leaves its height), d/dtheta1 = 19.5
    # plus the broad hill's slope times the peak's shift
    assert np.allclose(r["grad"][0, :2], fd, rtol=1e-4, atol=1e-4 * r["P_max"][0])
    assert abs(r["grad"][0, 1] - 19.5 * 1.0) < 1e-2


def test_hills_finds_every_turn_and_a_band_edge():
    f = np.array([20.0, 40.0, 60.0, 80.0, 100.0])
    p = np.array([5.0, 1.0, 2.0, 1.0, 3.0])
    g = np.array([-1.0, 0.1, 0.0, -0.1, 0.2])
    found = hills(f, p, g, (20.0, 100.0))
    edges = sorted(round(fc) for _, _, fc in found)
    assert edges[0] == 20 and edges[-1] == 100 and any(50 < e < 80 for e in edges)
    lvl1 = next_frequencies(f, p, g, 1, 8, (20.0, 100.0))
    assert lvl1.shape == (8,) and (lvl1 >= 20).all() and (lvl1 <= 100).all()


def test_stationary_point_falls_back_to_the_best_cell_at_a_band_edge():
    f = np.linspace(20.0, 30.0, 8)
    p = 100 - f  # falling: the maximum is the band edge
    fs, rows = stationary_point(f, p, -np.ones(8), np.stack([p, 2 * p], 1))
    assert fs == 20.0 and np.allclose(rows, [80.0, 160.0])
    fs, rows = stationary_point(f, -(f - 24.5) ** 2, -2 * (f - 24.5), (f - 24.5)[:, None] ** 2)
    assert abs(fs - 24.5) < 1e-9 and abs(rows[0]) < 1e-9
