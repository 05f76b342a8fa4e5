"""Paper 000 reproduced: the claims loss and its hinge terms on toy numbers, the peak fit, the
fitted configs against their own claims table, and ``jaxdea reproduce`` at reduced size."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from jaxdea.reproduce.claims import CLAIMS, Above, Claim, Near, loss, met, q, quantities_of
from jaxdea.reproduce.peaks import CASES

ROOT = Path(__file__).parents[1]
FITTED = ROOT / "configs" / "paper000"


def test_near_error_is_in_units_of_the_tolerance():
    n = Near("P:x:0.1", 18.7e-3, 0.05)
    assert float(n.error(18.7e-3)) == 0.0
    assert float(n.error(18.7e-3 * 1.05)) == pytest.approx(1.0)
    assert float(n.error(18.7e-3 / 1.05)) == pytest.approx(-1.0)
    assert n.holds(18.7e-3 * 1.049) and not n.holds(18.7e-3 * 1.051)
    f = Near("f:x:0.1", 130.0, 10.0, absolute=True)
    assert float(f.error(125.0)) == pytest.approx(-0.5)
    assert f.holds(139.9) and not f.holds(140.1)


def test_hinge_is_zero_with_the_margin_one_at_equality_and_grows_when_reversed():
    a = Above("P:big:0.1", "P:small:0.1", factor=2.0, margin=0.05)
    assert float(a.error(2.0 * math.exp(0.06), 1.0)) == 0.0      # holds with the margin
    assert float(a.error(2.0, 1.0)) == pytest.approx(1.0)        # equal: one
    assert float(a.error(2.0 * math.exp(0.025), 1.0)) == pytest.approx(0.5)
    assert float(a.error(1.0, 1.0)) == pytest.approx((0.05 + math.log(2)) / 0.05)
    assert a.holds(2.0 * 1.001, 1.0) and not a.holds(1.999, 1.0)
    const = Above("P:big:10", 18e-3)
    assert const.uses == ("P:big:10",)
    assert float(const.error(18e-3, 18e-3)) == pytest.approx(1.0)


def test_loss_sums_weighted_squared_terms_and_penalises_a_failed_design():
    claims = (Claim("a", "toy", "", (Near("P:x:1", 1.0, 0.1),), weight=2.0),
              Claim("b", "toy", "", (Above("P:x:1", "P:y:1", margin=0.1),)))
    qs = {"P:x:1": np.array([1.1, 1.0, np.nan]), "P:y:1": np.array([1.0, 1.0, 1.0])}
    got = np.asarray(loss(qs, claims, nan_penalty=1e3))
    e = math.log(1.1) / math.log1p(0.1)
    h = (0.1 - math.log(1.1)) / 0.1
    assert got[0] == pytest.approx(2.0 * e * e + h * h)
    assert got[1] == pytest.approx(0.0 + 1.0)
    assert got[2] == 1e3
    assert not met(claims[1], qs, 1) and not met(claims[0], qs, 2)
    qs["P:x:1"][0] = 1.09
    assert met(claims[0], qs, 0) and met(claims[1], qs, 0)


def _toy_table(p: dict) -> dict:
    """A peak table of one design with P_max ``p[case] = (light, heavy)`` in mW."""
    tab = {"P_max": {}, "f": {}, "P_in": {}, "local": {}}
    for case in CASES:
        lt, hv = p[case]
        tab["P_max"][case] = np.array([[lt, hv]]) * 1e-3
        tab["f"][case] = np.array([[130.0, 120.0]])
        tab["P_in"][case] = np.array([[1.0, 1.0]])
    tab["local"][("DCDEA-LS-A", 0.1)] = (np.array([6.3e-3]), np.array([70.0]))
    return tab


def test_the_paper_s_own_numbers_meet_every_claim():
    """A table built from the paper's statements (Figs 7-11, findings) meets all 16 claims
    and has zero loss; swapping finding 2a's ordering breaks exactly the claims that rest
    on it."""
    paper = {"SCDEA-LS": (24.0, 1.0), "DCDEA-RR": (9.0, 0.9), "DCDEA-LS-B": (8.0, 0.85),
             "DCDEA-LS-A": (18.7, 25.0), "DCDEA-RR-anti": (36.0, 3.0),
             "DCDEA-LS-anti": (20.0, 24.0), "DCDEA-LS-in": (30.0, 26.0)}
    qs = quantities_of(_toy_table(paper))
    qs[q("eta", "DCDEA-RR-anti", 0.1)] = np.array([0.05])
    assert all(met(c, qs) for c in CLAIMS), [c.name for c in CLAIMS if not met(c, qs)]
    assert float(np.asarray(loss(qs))[0]) < 1e-12
    swapped = dict(paper, **{"DCDEA-LS-in": (40.0, 26.0)})
    qs = quantities_of(_toy_table(swapped))
    qs[q("eta", "DCDEA-RR-anti", 0.1)] = np.array([0.05])
    broken = {c.name for c in CLAIMS if not met(c, qs)}
    assert broken == {"fig10-ls-in-30mW", "fig11-rr-anti-best", "finding-2a"}
    assert float(np.asarray(loss(qs))[0]) > 1.0


def test_parabola_vertex_of_the_fine_grid():
    from jaxdea.reproduce.peaks import _parabola  # noqa: PLC2701 - the fit itself

    f = np.tile(np.arange(120.0, 129.0), (2, 1))
    p = np.stack([5.0 - 0.1 * (f[0] - 124.3) ** 2, np.where(f[1] > 0, 1.0 + f[1], 0)])
    fv, pv = _parabola(f, p)
    assert fv[0] == pytest.approx(124.3) and pv[0] == pytest.approx(5.0)
    assert fv[1] == 128.0 and pv[1] == 129.0  # rising to the edge: the edge cell


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_the_fitted_configs_reproduce_their_claims_table_at_one_point():
    """configs/paper000/*.toml load, and the Fig 9 global-peak cell of the committed
    claims.csv (DCDEA-LS-A, M = 2 g, c = 0.1, 100 cycles) comes out again."""
    import jaxdea

    models = {k: jaxdea.load_config(FITTED / f"{k}.toml") for k in
              ("scdea_ls", "dcdea_rr", "dcdea_ls")}
    mu = {float(m.actuator.membrane.dielectric.mu_A) for m in models.values()}
    assert len(mu) == 1  # one material set shared by the three configurations
    assert "fitted" in (FITTED / "dcdea_ls.toml").read_text()
    rows = _rows(FITTED / "claims.csv")
    assert list(rows[0]) == ["claim", "case", "M_kg", "c_Ns_per_m", "f_Hz", "P_out_W", "met"]
    assert {r["case"] for r in rows} <= set(CASES)
    assert {r["met"] for r in rows} <= {"yes", "no"}
    row = next(r for r in rows if r["claim"] == "fig9-global")
    ds = jaxdea.sweep(models["dcdea_ls"], mass=float(row["M_kg"]),
                      damping=float(row["c_Ns_per_m"]), freq=[float(row["f_Hz"])], drive="A")
    assert int(ds["status"].values[0]) == 0
    assert float(ds["P_out"].values[0]) == pytest.approx(float(row["P_out_W"]), rel=1e-4)


def test_reproduce_at_reduced_size(tmp_path):
    """``jaxdea reproduce paper000`` end to end at reduced size: the five figures, the
    claims table with the exact columns, one row per number, and the maps."""
    from jaxdea.cli.main import main

    out = tmp_path / "p0"
    assert main(["reproduce", "paper000", "--out", str(out), "--size", "small", "--quiet",
                 "--configs", str(FITTED)]) == 0
    for name in ("fig6.png", "fig7.png", "fig9.png", "fig10.png", "fig11.png", "claims.md"):
        assert (out / name).stat().st_size > 1000, name
    rows = _rows(out / "claims.csv")
    assert list(rows[0]) == ["claim", "case", "M_kg", "c_Ns_per_m", "f_Hz", "P_out_W", "met"]
    assert {r["claim"] for r in rows} == {c.name for c in CLAIMS}
    assert all(float(r["P_out_W"]) > 0 for r in rows)
    md = (out / "claims.md").read_text()
    assert all(c.name in md for c in CLAIMS)
    # a second run into the same folder replaces the reproduction; a foreign folder is refused
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep")
    assert main(["reproduce", "paper000", "--out", str(foreign), "--size", "small",
                 "--quiet", "--configs", str(FITTED)]) == 2
    assert (foreign / "notes.txt").read_text() == "keep"
