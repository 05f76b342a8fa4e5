"""The lane-step's floor: what the engine's per-step bookkeeping costs above the solver step.

Issue 16, item 1. A copy of :func:`jaxdea.engine.lanes.run_protocol`'s ``lane_step`` (the
paper protocol's branch; no queue, no harvest; one pool of 128 lanes; DCDEA-LS drive A, 128
payloads at 60 Hz, every lane busy) in a plain ``fori_loop``, with its pieces switched on
and off:

- ``floor``: the Lawson RK4 step, the I-controller, the clip to the cycle's next node and
  the accept select only;
- ``all``: everything the engine's step does (periodicity residual and contraction rate,
  cycle-start state, Hermite extrema, returned energy, averaging window, Gent margin,
  blown-step NaN and ``done``);
- ``all_before``: ``all`` as the engine's step was before session 28 (whole states in the
  cycle-start and window records, the blown-step NaN written every step);
- ``all_rounds``: ``all`` in rounds of 16 steps (the engine's loop structure);
- ``all-X``: ``all`` without piece X.

Every variant is compiled first, then timed interleaved round by round (this machine's
speed drifts by +-20 % between minutes); best of ``--rounds``. The copy is not the engine
itself (``bench/lane_profile.py`` measures that).

    python bench/lane_floor.py [--rounds 3] [--steps 8000]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import time

ALL = ("res", "prev", "herm", "back", "window", "lockup", "blown")
LANES = 128
CYCLES, AVERAGE = 10**6, 2  # never finishes: every lane busy for every step


def make(model, parts: tuple[str, ...], n_step: int, rounds: bool, lean: bool = True):
    """The copied step with ``parts`` on, jitted over a pool of lanes for ``n_step`` steps.

    ``lean``: as the engine is now: the cycle-start record holds the dynamical states only,
    the window's the energy accumulators only, and a blown step sets a flag (the engine
    writes its NaN once per round). ``False``: as it was up to session 27 (both records the
    whole state; the NaN written in every step)."""
    import jax
    import jax.numpy as jnp

    from jaxdea.engine.lane_state import cycle_nodes
    from jaxdea.engine.metrics import dynamics, energies, hermite_extrema, periodicity_residual
    from jaxdea.engine.step_control import IController, charge_weight
    from jaxdea.solver import LawsonRK4, SemilinearTerm

    term = SemilinearTerm(model.vector_field, model.linearisation)
    solver, ctl = LawsonRK4(), IController(rtol=1e-6, dt_max=1e-3)
    y0 = model.initial_state()
    on = slice(0, 1)

    def where(mask, a, b):
        return jax.tree_util.tree_map(lambda x, y: jnp.where(mask, x, y), a, b)

    def step(L, ld, nodes):
        period = 1.0 / ld.drive.frequency
        target = jnp.min(jnp.where(nodes > L["u"] + 1e-12, nodes, 1.0))
        to_node = (target - L["u"]) * period
        clipped = L["h"] >= to_node
        h = jnp.where(clipped, to_node, L["h"])
        t0 = L["u"] * period
        y1, err, *_ = solver.step(term, t0, t0 + h, L["y"], ld, None, False)
        active = ~L["done"]
        accept, ok, h_next = ctl.adapt_step_size(L["y"], y1, err, h, L["h"], clipped, active,
                                                 charge_weight(ld.drive.frequency))
        y = where(accept, y1, L["y"])
        u = jnp.where(accept, jnp.where(clipped, target, L["u"] + h / period), L["u"])
        wrap = u >= 1.0 - 1e-12
        cycle = L["cycle"] + wrap.astype(jnp.int32)
        u = jnp.where(wrap, 0.0, u)
        N = dict(L, y=y, u=u, h=h_next, cycle=cycle)
        if "res" in parts:
            res = periodicity_residual(y, L["prev"])
            measured = wrap & jnp.isfinite(L["res"])
            ratio = jnp.where(measured, res / jnp.maximum(L["res"], 1e-300), L["ratio"])
            rate = jnp.where(measured, jnp.maximum(ratio, L["ratio"]), L["rate"])
            N.update(res=jnp.where(wrap, res, L["res"]), ratio=ratio, rate=rate)
        if "prev" in parts:
            N["prev"] = where(wrap, dynamics(y) if lean else y, L["prev"])
        in_window = accept & (L["cycle"] >= CYCLES - AVERAGE)
        if "herm" in parts:
            (x0, v0), (x1, v1) = model.payload_motion(L["y"]), model.payload_motion(y1)
            lo, hi = hermite_extrema(x0, v0, x1, v1, h)
            N["xmin"] = jnp.where(in_window, jnp.minimum(L["xmin"], lo), L["xmin"])
            N["xmax"] = jnp.where(in_window, jnp.maximum(L["xmax"], hi), L["xmax"])
        if "back" in parts:
            back = model.returned_energy(t0, h, L["y"], y1, ld, on)
            N["back"] = jnp.where(in_window, L["back"] + back, L["back"])
        if "window" in parts:
            start = wrap & (cycle == CYCLES - AVERAGE)
            N["window"] = where(start, energies(y) if lean else y, L["window"])
            N["wcycle"] = jnp.where(start, cycle, L["wcycle"])
        lockup = L["lockup"]
        if "lockup" in parts:
            lockup = lockup | (active & ~(model.lockup_margin(y) > 0))
            N["lockup"] = lockup
        steps = L["steps"] + active.astype(jnp.int32)
        N["steps"] = steps
        if "blown" in parts:
            blown = active & ~ok & (h < 1e-12 * period)
            if not lean:
                N["y"] = jax.tree_util.tree_map(lambda a: jnp.where(blown, jnp.nan, a), N["y"])
            N["done"] = (L["done"] | (cycle >= CYCLES) | lockup | blown
                         | (steps >= 5_000_000))
        return N

    @jax.jit
    def run(ld):
        nodes = jax.vmap(cycle_nodes)(ld)
        ys = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (LANES,) + a.shape), y0)
        z = jnp.zeros(LANES)
        L = dict(y=ys, u=z, h=jnp.full(LANES, 1e-5), cycle=jnp.zeros(LANES, jnp.int32),
                 done=jnp.zeros(LANES, bool), res=z + jnp.inf, ratio=z + 1.0, rate=z + 1.0,
                 prev=dynamics(ys) if lean else ys, window=energies(ys) if lean else ys,
                 wcycle=jnp.zeros(LANES, jnp.int32), xmin=z + jnp.inf,
                 xmax=z - jnp.inf, back=jnp.zeros((LANES, 1)), lockup=jnp.zeros(LANES, bool),
                 steps=jnp.zeros(LANES, jnp.int32))
        vs = jax.vmap(step)
        if not rounds:
            return jax.lax.fori_loop(0, n_step, lambda _, ln: vs(ln, ld, nodes), L)
        return jax.lax.fori_loop(0, n_step // 16, lambda _, ln: jax.lax.fori_loop(
            0, 16, lambda _, m: vs(m, ld, nodes), ln), L)

    return run


def main() -> None:
    import jaxdea
    from lane_profile import workload

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=8000, help="steps per timed run")
    args = ap.parse_args()
    jaxdea.use_cpu_cores(1)  # one device, no Eigen pool (as the map's devices run)
    n_step = max(16, args.steps // 16 * 16)
    cfg, loads = workload(LANES)  # the cells of bench/lane_profile.py
    variants = {"floor": ((), False, True), "all": (ALL, False, True),
                "all_before": (ALL, False, False), "all_rounds": (ALL, True, True)}
    for p in ALL:
        variants["all-" + p] = (tuple(x for x in ALL if x != p), False, True)
    progs = {}
    for k, (parts, rounds, lean) in variants.items():
        progs[k] = make(cfg.actuator, parts, n_step, rounds, lean)
        progs[k](loads)["u"].block_until_ready()  # compile and first call, untimed
    best = {k: float("inf") for k in progs}
    for _ in range(args.rounds):
        for k, run in progs.items():
            t0 = time.perf_counter()
            run(loads)["u"].block_until_ready()
            best[k] = min(best[k], 1e9 * (time.perf_counter() - t0) / (n_step * LANES))
    for k, v in best.items():
        print(f"{k:12s} {v:7.1f} ns per lane-step ({v - best['all']:+7.1f} against all)")
    print("RESULT " + " ".join(f"{k.replace('-', '_minus_')}_ns={v:.1f}"
                               for k, v in best.items())
          + f" all_over_floor={best['all'] / best['floor']:.2f}")


if __name__ == "__main__":
    main()
