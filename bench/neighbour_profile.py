"""Where a warm-started power map's time goes (issue 16, item 2: ``start="neighbour"``).

Workload: DCDEA-LS, drive A, ``protocol="periodic", start="neighbour"``, the full map's first
``--masses`` masses (of 50, log-spaced 0.1-10 g) x all 50 dampings x every 10th frequency of
its 0.2 Hz grid: with the default 25 masses this is exactly one chunk of
``bench/full_map_slice.py``'s slice (125 000 cells), run through ``jaxdea.powermap`` on one
JAX device per core after a warm-up on a small grid (so the chunk's own programs compile in
the timed run, as they do for a user).

The stages of :func:`jaxdea.engine.warmstart.neighbour_chain` are timed by wrapping them in
this process (the engine is not changed):

- ``rest``: :func:`~jaxdea.engine.periodic.periodic_cells` calls, i.e. the chain's first
  stage's from-rest solves (its first mass, and cells of the others whose continuation
  failed; with Newton shooting for the Jacobians the chord iterations start from:
  ``first_stage``; the continuation along the masses is chord work, counted below) and
  the batches solved from rest after the chain (cells below ``REST_BELOW`` and cells whose
  chord iteration failed: ``rest_after_chain``);
- ``chord``: the chord iterations of the first stage's later masses
  (:func:`~jaxdea.engine.chord.chord_cells`) and of the later stages
  (:func:`~jaxdea.engine.warmstart.chord_columns`), of which ``chord_periods`` is the plain
  one-period engine calls and ``chord_shots`` the true Jacobians of cells that arrived
  without one or whose stability is in doubt; the rest of ``chord`` is host work (Broyden
  updates, Newton steps, Floquet radii);
- ``compile``: XLA's compile time inside the timed run (JAX's backend-compile events),
  which falls inside the stages above.

Each is printed in seconds and as a share of the wall time; the engine's steps per second
in the chord periods against the from-rest batches after the chain (same engine, same
chunk, no compile: the baseline measured in the same run).

    python bench/neighbour_profile.py [--masses 25]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import collections
import time
from pathlib import Path

import jax
import numpy as np

import jaxdea
from jaxdea.engine import chord, warmstart

ROOT = Path(__file__).resolve().parents[1]


class Clock:
    """Seconds per named stage, and the calls' cells and steps where a stage reports them."""

    def __init__(self):
        self.seconds = collections.defaultdict(float)
        self.calls = collections.defaultdict(list)
        self.compile = 0.0
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, name: str, secs: float, **_) -> None:
        if name == "/jax/core/compile/backend_compile_duration":
            self.compile += secs

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()
        self.compile = 0.0

    def wrap(self, name: str, fn, steps=None):
        def timed(*args, **kwargs):
            compile0, t0 = self.compile, time.perf_counter()
            out = fn(*args, **kwargs)
            dt = time.perf_counter() - t0
            self.seconds[name] += dt
            self.calls[name].append((dt, self.compile - compile0,
                                     None if steps is None else steps(args, kwargs, out)))
            return out
        return timed

    def wrap_generator(self, name: str, fn):
        """As :meth:`wrap` for a generator: the time spent inside it, between its yields."""
        def timed(*args, **kwargs):
            gen = fn(*args, **kwargs)
            while True:
                t0 = time.perf_counter()
                try:
                    item = next(gen)
                except StopIteration:
                    return
                finally:
                    self.seconds[name] += time.perf_counter() - t0
                yield item
        return timed


def _period_steps(args, kwargs, out) -> int:
    """Steps of the active cells of a one-period call
    ``(program, actuator, loadings, y, active)``."""
    return int(np.sum(np.where(np.asarray(args[4]), np.asarray(out.steps), 0)))


def _rest_steps(args, kwargs, out) -> tuple[bool, int]:
    """Whether a ``periodic_cells`` call is a chain's first stage (it asks for Jacobians),
    and the steps of its active cells."""
    res = out[0] if isinstance(out, tuple) else out
    active = kwargs.get("active")
    steps = np.asarray(res.steps)
    return (bool(kwargs.get("with_jacobian")),
            int(np.sum(steps if active is None else np.where(active, steps, 0))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--masses", type=int, default=25, help="masses of the 50 (default 25)")
    args = ap.parse_args()
    if not 1 <= args.masses <= 50:
        raise SystemExit(f"--masses must be in 1..50, got {args.masses}")
    n_dev = jaxdea.use_cpu_cores()
    clock = Clock()
    sharded = chord.cell_sharded

    def cell_sharded(fn, devices):
        run = sharded(fn, devices)
        return clock.wrap("chord_shots", run) if fn.__name__ == "shoot_period" else run

    chord.cell_sharded = cell_sharded
    chord.one_period = clock.wrap("chord_periods", chord.one_period, _period_steps)
    warmstart.periodic_cells = clock.wrap("rest", warmstart.periodic_cells, _rest_steps)
    warmstart.chord_cells = clock.wrap("chord", warmstart.chord_cells)
    warmstart.chord_columns = clock.wrap_generator("chord", warmstart.chord_columns)

    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    mass, damping = np.logspace(-4, -2, 50)[:args.masses], np.logspace(-1, 1, 50)
    freq = np.round(1.0 + 0.2 * np.arange(996), 6)[::10]
    kw = dict(mass=mass, damping=damping, freq=freq, drive="A", protocol="periodic",
              start="neighbour", progress=False)
    jaxdea.powermap(model, **{**kw, "mass": mass[:2] * 1.05, "damping": damping[:2],
                              "freq": freq[:8]})
    clock.reset()
    t0 = time.perf_counter()
    ds = jaxdea.powermap(model, **kw)
    wall = time.perf_counter() - t0
    steps = float(ds.steps.values.sum())
    first = [c for c in clock.calls["rest"] if c[2][0]]
    rest = [(dt, comp, n) for dt, comp, (is_first, n) in clock.calls["rest"] if not is_first]
    periods = clock.calls["chord_periods"]
    parts = {
        "first_stage": sum(c[0] for c in first),
        "rest_after_chain": sum(c[0] for c in rest),
        "chord_periods": clock.seconds["chord_periods"],
        "chord_shots": clock.seconds["chord_shots"],
        "chord_host": (clock.seconds["chord"] - clock.seconds["chord_periods"]
                       - clock.seconds["chord_shots"]),
    }
    parts["other"] = wall - sum(parts.values())
    print(f"neighbour map: {ds.P_out.size} cells on {n_dev} device(s) in {wall:.1f} s, "
          f"{steps:.3g} steps (primal), XLA compile inside it {clock.compile:.1f} s "
          f"({100 * clock.compile / wall:.0f} %)")
    for name, sec in parts.items():
        print(f"  {name:18s} {sec:7.1f} s  {100 * sec / wall:4.0f} %")
    # steps per second of the engine, compile excluded: chord periods against the from-rest
    # batches after the chain (the first stage also shoots: tangents are not counted steps)
    chord_rate = (sum(c[2] for c in periods) / max(sum(c[0] - c[1] for c in periods), 1e-9))
    rest_rate = sum(c[2] for c in rest) / max(sum(c[0] - c[1] for c in rest), 1e-9)
    print(f"steps/s (all devices, compile excluded): chord periods {chord_rate:.3g} in "
          f"{len(periods)} calls, from-rest batches {rest_rate:.3g} in {len(rest)} calls: "
          f"ratio {chord_rate / max(rest_rate, 1e-9):.2f}")
    print("RESULT " + " ".join(
        [f"cells={ds.P_out.size}", f"devices={n_dev}", f"wall_s={wall:.1f}",
         f"compile_s={clock.compile:.1f}", f"steps={steps:.3g}"]
        + [f"{k}_s={v:.1f}" for k, v in parts.items()]
        + [f"chord_calls={len(periods)}", f"chord_steps_per_s={chord_rate:.3g}",
           f"rest_steps_per_s={rest_rate:.3g}",
           f"chord_over_rest_rate={chord_rate / max(rest_rate, 1e-9):.2f}"]))


if __name__ == "__main__":
    main()
