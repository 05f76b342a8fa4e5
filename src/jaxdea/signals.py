"""Drive voltages.

Paper 000 drives its cones with a unipolar square wave (0 / V0, 50 % duty, "on" in the first
part of each period); double cones may drive both membranes with a relative phase. A drive
evaluates to one source voltage per membrane, and knows where its discontinuities are so the
integrator can put step boundaries on them (DESIGN: never let a controller find edges by
rejection).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


class SquareWave(eqx.Module):
    """Unipolar square wave per membrane: ``amplitude`` while on, 0 while off.

    ``amplitude`` and ``phase`` have one entry per membrane (amplitude 0 = not driven).
    Membrane ``j`` is on while ``frac(f t - phase_j / (2 pi)) < duty``: a positive phase
    delays that membrane's wave by ``phase_j / (2 pi)`` periods (pi = antiphase).
    """

    amplitude: Array
    frequency: ArrayLike
    duty: ArrayLike
    phase: Array

    @property
    def period(self) -> Array:
        return 1.0 / self.frequency

    def cycle_position(self, t: ArrayLike) -> Array:
        """Position of each membrane's wave in its own cycle, in [0, 1)."""
        s = t * self.frequency - self.phase / (2.0 * jnp.pi)
        return s - jnp.floor(s)

    def __call__(self, t: ArrayLike) -> Array:
        on = self.cycle_position(t) < self.duty
        return jnp.where(on, self.amplitude, 0.0)

    def edge_fractions(self) -> Array:
        """Switching instants within one period of membrane A's cycle, as fractions in [0, 1).

        Two per membrane (on and off edge), driven or not; duplicates are harmless.
        """
        on = self.phase / (2.0 * jnp.pi)
        edges = jnp.concatenate([on, on + self.duty])
        return edges - jnp.floor(edges)


# --- Drives of the viscoelastic models (papers 001, 002, 004) ------------------------------


def _is_concrete(x) -> bool:
    import jax

    return not isinstance(x, jax.core.Tracer)


class MultiSine(eqx.Module):
    """Piecewise multi-sine of paper 002 eq 25 (= paper 001's driving voltage).

    With ``T = sum_i 1/f_i`` and ``t_m = rem(t, T)``, segment ``i`` lasts ``1/f_i`` and reads
    ``v = a_i sin(f_i pi (t_m - sum_{j<i} 1/f_j))``: one unipolar half-sine hump per segment.
    ``a`` (V) and ``f`` (Hz) are 1-D with the same length (any number of segments).
    """

    a: Array
    f: Array

    def __check_init__(self):
        a, f = jnp.asarray(self.a), jnp.asarray(self.f)
        if a.ndim != 1 or f.ndim != 1 or a.shape[0] == 0 or f.shape[0] == 0:
            raise ValueError(f"MultiSine needs 1-D amplitudes a_i and frequencies f_i, got "
                             f"a of shape {a.shape} and f of shape {f.shape}")
        if a.shape != f.shape:
            raise ValueError(f"MultiSine needs one f_i per a_i: got {a.shape[0]} amplitude(s) "
                             f"and {f.shape[0]} frequenc(ies); a_i or f_i missing")
        if _is_concrete(f) and not bool(jnp.all(jnp.isfinite(f) & (f > 0))):
            raise ValueError(f"MultiSine frequencies f_i must be finite and > 0 Hz, got {f}")
        if _is_concrete(a) and not bool(jnp.all(jnp.isfinite(a))):
            raise ValueError(f"MultiSine amplitudes a_i must be finite, got {a}")

    @property
    def period(self) -> Array:
        return jnp.sum(1.0 / self.f)

    def _starts(self) -> tuple[Array, Array]:
        ends = jnp.cumsum(1.0 / self.f)
        return ends - 1.0 / self.f, ends

    def __call__(self, t: ArrayLike) -> Array:
        tm = jnp.mod(t, self.period)
        starts, ends = self._starts()
        inside = (tm >= starts) & (tm < ends)
        seg = self.a * jnp.sin(self.f * jnp.pi * (tm - starts))
        return jnp.sum(jnp.where(inside, seg, 0.0))

    def kink_times(self, cycles: int) -> Array:
        """Segment joints (derivative jumps) in ``[0, cycles T]``, for ``diffrax`` ``jump_ts``."""
        _, ends = self._starts()
        k = jnp.arange(cycles)[:, None] * self.period
        return jnp.concatenate([jnp.zeros(1), (k + ends[None, :]).ravel()])


class Sine(eqx.Module):
    """Plain sine ``v = offset + amplitude sin(2 pi frequency t + phase)`` (V)."""

    amplitude: ArrayLike
    frequency: ArrayLike
    offset: ArrayLike = 0.0
    phase: ArrayLike = 0.0

    def __check_init__(self):
        f = self.frequency
        if _is_concrete(f) and not bool(jnp.all(jnp.asarray(f) > 0)):
            raise ValueError(f"Sine frequency must be > 0 Hz, got {f}")

    @property
    def period(self) -> Array:
        return 1.0 / jnp.asarray(self.frequency)

    def __call__(self, t: ArrayLike) -> Array:
        return self.offset + self.amplitude * jnp.sin(2.0 * jnp.pi * self.frequency * t
                                                      + self.phase)

    def kink_times(self, cycles: int) -> Array:
        return jnp.zeros(1)


#: Triangular voltage patterns of paper 004 Fig 3, as the voltage levels (fractions of the
#: peak) visited in one period at a constant |dV/dt|. Fig 3 is missing from the text; the
#: levels are chosen to match its caption (see docs/models.md).
VOLTAGE_PATTERNS: dict[str, tuple[float, ...]] = {
    # one maximum peak
    "vp1": (0.0, 1.0, 0.0),
    # three increasing local maximum peaks
    "vp2": (0.0, 0.6, 0.3, 0.8, 0.5, 1.0, 0.0),
    # three decreasing local minimum peaks
    "vp3": (0.0, 1.0, 0.5, 0.8, 0.3, 0.6, 0.0),
    # increasing then decreasing local maximum peaks
    "vp4": (0.0, 0.5, 0.25, 0.75, 0.5, 1.0, 0.5, 0.75, 0.25, 0.5, 0.0),
}


class TriangularPattern(eqx.Module):
    """Periodic triangular voltage pattern VP1-VP4 of paper 004 (Fig 3), piecewise linear.

    ``peak`` (V) and ``period`` (s) are parameters; ``levels`` (static) are the visited levels
    as fractions of ``peak``, joined at a constant |slope| so segment durations are
    proportional to the level change. Build one with :func:`voltage_pattern`.
    """

    peak: ArrayLike
    period: ArrayLike
    levels: tuple[float, ...] = eqx.field(static=True, default=VOLTAGE_PATTERNS["vp1"])

    def __check_init__(self):
        if len(self.levels) < 2:
            raise ValueError("a triangular pattern needs at least two levels")
        if _is_concrete(self.period) and not bool(jnp.all(jnp.asarray(self.period) > 0)):
            raise ValueError(f"pattern period must be > 0 s, got {self.period}")

    def fractions(self) -> Array:
        """Breakpoint positions within one period, in [0, 1]."""
        lv = jnp.asarray(self.levels)
        d = jnp.abs(jnp.diff(lv))
        return jnp.concatenate([jnp.zeros(1), jnp.cumsum(d) / jnp.sum(d)])

    def __call__(self, t: ArrayLike) -> Array:
        s = jnp.mod(t / self.period, 1.0)
        return self.peak * jnp.interp(s, self.fractions(), jnp.asarray(self.levels))

    def kink_times(self, cycles: int) -> Array:
        """Breakpoints (slope jumps) in ``[0, cycles T]``, for ``diffrax`` ``jump_ts``."""
        fr = self.fractions()[:-1]
        k = jnp.arange(cycles + 1)[:, None]
        return ((k + fr[None, :]).ravel()) * self.period


def voltage_pattern(name: str, peak: ArrayLike, period: ArrayLike) -> TriangularPattern:
    """Paper 004's pattern ``name`` (``vp1`` ... ``vp4``) with the given peak (V) and period (s)."""
    key = name.lower()
    if key not in VOLTAGE_PATTERNS:
        raise ValueError(f"unknown voltage pattern {name!r}; allowed: "
                         f"{', '.join(VOLTAGE_PATTERNS)}")
    return TriangularPattern(jnp.asarray(peak, float), jnp.asarray(period, float),
                             VOLTAGE_PATTERNS[key])
