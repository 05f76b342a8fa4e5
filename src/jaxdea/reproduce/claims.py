"""Paper 000's published numbers and findings as checkable claims, and the calibration loss
built from them (Sections III-IV of seed 000; the readings are in ``docs/paper000.md``).

A claim rests on *quantities* of a peak table (:func:`jaxdea.reproduce.peaks.peak_table`),
named ``"P:<case>:<c>"`` (P_max, W), ``"f:<case>:<c>"`` (its frequency, Hz), ``"L:<case>:<c>"``
and ``"fL:<case>:<c>"`` (a local maximum and its frequency), ``"Pin:<case>:<c>"`` (P_in at
the peak) and, derived from those (:func:`derive`), ``"eta:<case>:<c>"`` (the efficiency at
the peak) and ``"R:DCDEA-RR-anti:<c>"`` (antiphase over single actuation). Two kinds:

- :class:`Near`: a published value, met within a relative (or, for a frequency, absolute)
  tolerance; its loss term is the squared error in units of the tolerance,
  ``(log(q / value) / log(1 + tol))^2`` or ``((q - value) / tol)^2``;
- :class:`Above`: an ordering ``q_big > factor * q_small`` (also "more than 18 mW", with a
  constant); its loss term is the squared hinge ``max(0, (m - log(q_big / (factor q_small))) /
  m)^2`` with a margin ``m`` in log units: zero once the ordering holds with that margin,
  one when the two are equal.

:func:`loss` sums the terms of every claim in :data:`CLAIMS`, weighted.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

__all__ = ["CLAIMS", "LIGHT", "HEAVY", "MASS", "Above", "Claim", "Near", "claim_terms",
           "derive", "loss", "met", "quantities_of"]

#: Paper 000's light and heavy payload damping (N s/m) and the payload mass of Figs 8-11 (kg).
LIGHT, HEAVY, MASS = 0.1, 10.0, 2e-3


def q(kind: str, case: str, c: float) -> str:
    """The name of a quantity: ``q("P", "DCDEA-RR", 0.1) == "P:DCDEA-RR:0.1"``."""
    return f"{kind}:{case}:{c:g}"


@dataclasses.dataclass(frozen=True)
class Near:
    """Quantity ``of`` is ``value`` within ``tol`` (relative; absolute if ``absolute``)."""

    of: str
    value: float
    tol: float
    absolute: bool = False

    def error(self, x):
        if self.absolute:
            return (x - self.value) / self.tol
        return jnp.log(x / self.value) / math.log1p(self.tol)

    def holds(self, x) -> bool:
        return bool(abs(float(self.error(x))) <= 1.0)

    @property
    def uses(self) -> tuple[str, ...]:
        return (self.of,)


@dataclasses.dataclass(frozen=True)
class Above:
    """Quantity ``big`` exceeds ``factor`` times quantity ``small`` (or the constant
    ``small`` when it is a number); the loss keeps a log ``margin``."""

    big: str
    small: str | float
    factor: float = 1.0
    margin: float = 0.05

    def gap(self, big, small):
        """``log(big / (factor * small))``: positive where the ordering holds."""
        return jnp.log(big) - jnp.log(self.factor * small)

    def error(self, big, small):
        return jnp.maximum(0.0, (self.margin - self.gap(big, small)) / self.margin)

    def holds(self, big, small) -> bool:
        return bool(float(self.gap(big, small)) > 0.0)

    @property
    def uses(self) -> tuple[str, ...]:
        return (self.big,) if not isinstance(self.small, str) else (self.big, self.small)


@dataclasses.dataclass(frozen=True)
class Claim:
    """One statement of the paper: its label, where it is made, the text, and its parts (all
    must hold for the claim to be met)."""

    name: str
    where: str
    text: str
    parts: tuple
    weight: float = 1.0


def _above(big, small, factor=1.0, margin=0.05):
    return Above(big, small, factor, margin)


def _P(case: str, c: float) -> str:
    return q("P", case, c)


SC, RR, LSA, LSB = "SCDEA-LS", "DCDEA-RR", "DCDEA-LS-A", "DCDEA-LS-B"
RRX, LSX, LSI = "DCDEA-RR-anti", "DCDEA-LS-anti", "DCDEA-LS-in"

#: Every claim of paper 000 that the model is calibrated to and checked against.
CLAIMS: tuple[Claim, ...] = (
    Claim("fig9-global", "Fig 9", "DCDEA-LS-A, c = 0.1: global P_out maximum of 18.7 mW near "
          "130 Hz", (Near(_P(LSA, LIGHT), 18.7e-3, 0.05),
                     Near(q("f", LSA, LIGHT), 130.0, 10.0, absolute=True)), 2.0),
    Claim("fig9-local", "Fig 9", "DCDEA-LS-A, c = 0.1: local P_out maximum of 6.3 mW near "
          "70 Hz", (Near(q("L", LSA, LIGHT), 6.3e-3, 0.05),
                    Near(q("fL", LSA, LIGHT), 70.0, 10.0, absolute=True)), 2.0),
    Claim("fig7-fall", "Fig 7", "P_max of SCDEA-LS, DCDEA-RR and DCDEA-LS-B falls sharply "
          "with c (here: more than 3-fold from c = 0.1 to 10)",
          tuple(_above(_P(k, LIGHT), _P(k, HEAVY), 3.0) for k in (SC, RR, LSB))),
    Claim("fig7-below-sc", "Fig 7", "DCDEA-RR and DCDEA-LS-B lie below SCDEA-LS (c = 0.1)",
          (_above(_P(SC, LIGHT), _P(RR, LIGHT)), _above(_P(SC, LIGHT), _P(LSB, LIGHT)))),
    Claim("fig7-lsa-rises", "Fig 7", "DCDEA-LS-A: P_max rises with c",
          (_above(_P(LSA, HEAVY), _P(LSA, LIGHT)),)),
    Claim("fig7-lsa-18mW", "Fig 7", "DCDEA-LS-A at c = 10: P_max over 18 mW",
          (_above(_P(LSA, HEAVY), 18e-3),)),
    Claim("fig7-lsa-20x", "Fig 7", "DCDEA-LS-A at c = 10: more than 20-fold the direct "
          "drives", tuple(_above(_P(LSA, HEAVY), _P(k, HEAVY), 20.0) for k in (SC, RR, LSB))),
    Claim("fig10-rr-4x", "Fig 10", "DCDEA-RR antiphase: about 4-fold RR single actuation "
          "(c = 0.1; here within 25 %)",
          (Near(q("R", RRX, LIGHT), 4.0, 0.25),)),
    Claim("fig10-ls-anti", "Fig 10", "DCDEA-LS antiphase: slightly below its single "
          "actuation (LS-A) except at light damping (here: above at c = 0.1; 0.8-1x at "
          "c = 10)", (_above(_P(LSX, LIGHT), _P(LSA, LIGHT)),
                      _above(_P(LSA, HEAVY), _P(LSX, HEAVY), 1.0, 0.02),
                      _above(_P(LSX, HEAVY), _P(LSA, HEAVY), 0.8, 0.02))),
    Claim("fig10-ls-in-30mW", "Fig 10", "DCDEA-LS in-phase: P_max of about 30 mW at light "
          "damping (here within 15 %)", (Near(_P(LSI, LIGHT), 30e-3, 0.15),)),
    Claim("fig10-ls-in-light", "Fig 10", "DCDEA-LS in-phase improves on single actuation "
          "only at light damping (here: above LS-A at c = 0.1; within 10 % at c = 10)",
          (_above(_P(LSI, LIGHT), _P(LSA, LIGHT)),
           _above(_P(LSI, HEAVY), _P(LSA, HEAVY), 1 / 1.1, 0.02),
           _above(_P(LSA, HEAVY), _P(LSI, HEAVY), 1 / 1.1, 0.02))),
    Claim("fig11-rr-anti-best", "Fig 11", "M = 2 g: DCDEA-RR antiphase has the highest "
          "P_max and efficiency of the three double cases (over c = 0.1 and 10)",
          tuple(_above(_P(RRX, LIGHT), _P(k, c)) for k in (LSX, LSI) for c in (LIGHT, HEAVY))
          + tuple(_above(q("eta", RRX, LIGHT), q("eta", k, LIGHT), 1.0, 0.02)
                  for k in (LSX, LSI))),
    Claim("finding-1a", "Sec IV", "Single actuation, low damping: SCDEA-LS above DCDEA-RR "
          "and DCDEA-LS (direct drive, B), DCDEA-LS the lowest",
          (_above(_P(SC, LIGHT), _P(RR, LIGHT)), _above(_P(RR, LIGHT), _P(LSB, LIGHT)))),
    Claim("finding-1b", "Sec IV", "Single actuation, high damping: DCDEA-LS (indirect "
          "drive, A) the highest", tuple(_above(_P(LSA, HEAVY), _P(k, HEAVY))
                                         for k in (SC, RR, LSB))),
    Claim("finding-2a", "Sec IV", "Double actuation, low damping: DCDEA-RR antiphase above "
          "DCDEA-LS anti- and in-phase", tuple(_above(_P(RRX, LIGHT), _P(k, LIGHT))
                                              for k in (LSX, LSI))),
    Claim("finding-2b", "Sec IV", "Double actuation, high damping: DCDEA-LS in-phase the "
          "highest", tuple(_above(_P(LSI, HEAVY), _P(k, HEAVY)) for k in (RRX, LSX))),
)


def quantities_of(table: dict, dampings=(LIGHT, HEAVY)) -> dict[str, np.ndarray]:
    """The named quantities (arrays over designs) of a peak table: ``P``, ``f`` and
    ``Pin`` (P_in at the peak) per case and damping, ``L`` / ``fL`` of its local maxima, and
    what :func:`derive` computes from them."""
    out = {}
    for case, p in table["P_max"].items():
        for j, c in enumerate(dampings):
            out[q("P", case, c)] = p[:, j]
            out[q("f", case, c)] = table["f"][case][:, j]
            out[q("Pin", case, c)] = table["P_in"][case][:, j]
    for (case, c), (p, f) in table["local"].items():
        out[q("L", case, c)], out[q("fL", case, c)] = p, f
    derive(out, dampings)
    return out


def derive(qs: dict, dampings=(LIGHT, HEAVY)) -> None:
    """Fill, in place, the quantities computed from others: the efficiency at each peak
    ``eta = P / Pin`` and the ratio ``R`` of DCDEA-RR antiphase to single actuation (after
    a peak's P or Pin was replaced, call it again)."""
    for key in list(qs):
        if key.startswith("Pin:"):
            _, case, c = key.split(":")
            qs[f"eta:{case}:{c}"] = qs[f"P:{case}:{c}"] / qs[key]
    for c in dampings:
        a, b = q("P", RRX, c), q("P", RR, c)
        if a in qs and b in qs:
            qs[q("R", RRX, c)] = qs[a] / qs[b]


def claim_terms(claim: Claim, qs: dict) -> list:
    """The errors of the parts of ``claim`` (arrays over designs; 0 = met with margin)."""
    out = []
    for part in claim.parts:
        if isinstance(part, Near):
            out.append(part.error(qs[part.of]))
        else:
            small = qs[part.small] if isinstance(part.small, str) else part.small
            out.append(part.error(qs[part.big], small))
    return out


def loss(qs: dict, claims=CLAIMS, nan_penalty: float = 1e3):
    """The calibration loss: ``sum_claims weight * sum_parts error^2`` (arrays over
    designs); a design whose quantities are not all finite (a failed cell) gets
    ``nan_penalty`` instead."""
    total = 0.0
    for claim in claims:
        for e in claim_terms(claim, qs):
            total = total + claim.weight * e * e
    return jnp.where(jnp.isfinite(total), total, nan_penalty)


def met(claim: Claim, qs: dict, i: int = 0) -> bool:
    """Whether ``claim`` holds for design ``i`` of the quantities (no margins)."""
    ok = True
    for part in claim.parts:
        if isinstance(part, Near):
            x = float(np.asarray(qs[part.of])[i])
            ok &= math.isfinite(x) and part.holds(x)
        else:
            b = float(np.asarray(qs[part.big])[i])
            s = float(np.asarray(qs[part.small])[i]) if isinstance(part.small, str) \
                else part.small
            ok &= math.isfinite(b) and math.isfinite(s) and part.holds(b, s)
    return bool(ok)
