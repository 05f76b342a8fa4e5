"""What a JAX user writes without jaxdea: a plain ``jax.vmap`` of ``diffrax.diffeqsolve``.

The baseline of the benches' ``diffrax_ratio`` (issue 16): the same equations as jaxdea
(:meth:`jaxdea.ConeActuator.vector_field`, energies as ODE states) from the same rest state,
over the same cells, integrated by diffrax's Tsit5 with a PID controller that steps onto every
square-wave edge (``jump_ts``), one ``diffeqsolve`` per cell under ``jax.vmap``. P_out and P_in
are jaxdea's: means over the last ``average`` cycles from accumulator differences (the state
saved at the window start and at the end). P_in counts no energy recovery (the integral of
``max(Phi i, 0)``, as in tests/scipy_reference.py): that needs one more accumulator per
membrane, ``e_pos``, which the user adds next to jaxdea's signed ``energy_in``.

Tolerances: per-component absolute tolerances, as a user brings them to a state whose
components span 1e-7 C to 1: the solve runs on the state divided by :data:`SCALES` (the
component scales of tests/scipy_reference.py's ``state_scales``), so diffrax's scalar ``atol``
is ``atol * scale`` per component, ``atol = rtol``. :data:`RTOL` = 1e-6 keeps P_out and P_in
within the benches' 3e-4 of LSODA with margin (looser ones cross it erratically, for a few %
fewer steps; the measurements are at :data:`RTOL`). PID coefficients: the ``pcoeff=0.3,
icoeff=0.3`` that diffrax's documentation suggests for mildly stiff problems (the RC
transient after each edge makes this one so; measured against the default I controller at
:data:`PCOEFF`).

    python bench/diffrax_baseline.py --quick

DCDEA-LS, drive A, M = 2 g, c = 0.1 N s/m, 6 frequencies 20-200 Hz, 20 cycles (mean of the
last 5): P_out, P_in per cell from diffrax, jaxdea (``sweep(..., early_exit=None)``: every
cell runs all cycles) and LSODA (tests/scipy_reference.py, rtol 1e-8), their relative
differences, ns per step of each, and one line ``RESULT diffrax_ratio=... diffrax_err=...
jaxdea_err=...``. Wall times are second calls (compile excluded).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxdea
from jaxdea import ConeState, Loading, Model

ROOT = Path(__file__).resolve().parents[1]

#: Component scales of the state (SI), tests/scipy_reference.py's ``state_scales``: the
#: absolute tolerance of a component is ``atol`` times its scale.
SCALES = dict(q=1e-3, v=1e-2, charge=1e-7, xi_m=1.0, xi_el=1.0, payload_work=1e-4, v2=1e-4,
              energy_in=1e-4, e_pos=1e-4)
#: Default relative tolerance (``atol = rtol`` in scaled units). Chosen on the --quick cells
#: (DCDEA-LS, M 2 g, c 0.1, 6 frequencies 20-200 Hz, 20 cycles) against LSODA rtol 1e-8: max
#: relative error on P_out and P_in and total steps, PID 0.3/0.3 (I controller 0/1):
#: rtol 1e-5: 1.6e-3, 22030 steps; 5e-6: 2.1e-3 (1.4e-3), 22914 (23818); 3e-6: 2.9e-4 (7.1e-4),
#: 23350 (24280); 2e-6: 2.6e-5 (4.4e-4), 23998 (24632); 1e-6: 1.7e-5 (6.5e-5), 24842 (25385);
#: 1e-7: 9.0e-6 (8.4e-6), 29268 (28258). jaxdea at its defaults: 6.8e-4 (the 200 Hz cell;
#: 1.1e-4 elsewhere). Above 1e-6 the error is erratic (edges vs steps) and crosses the benches'
#: 3e-4 target; 1e-6 stays well inside it for 6 % more steps than 3e-6 (the step count hardly
#: depends on rtol here: the RC transient after each edge and Tsit5's stability limit set it),
#: so 1e-6: at least as accurate as jaxdea (max over the cells), at a cost within a few %
#: of the loosest tolerance that would match jaxdea's accuracy.
RTOL = 1e-6
#: PID coefficients: diffrax's documentation suggests ``pcoeff=0.3, icoeff=0.3`` for mildly
#: stiff problems. Measured on the --quick cells: 2-4 % fewer steps than the default I
#: controller (pcoeff 0, icoeff 1) from rtol 1e-6 to 5e-6, and a steadier error (above).
PCOEFF, ICOEFF = 0.3, 0.3


def _scale_tree(y: ConeState, e_pos: jax.Array) -> tuple[ConeState, jax.Array]:
    """The scale of every component of the (state, e_pos) pair, as a pytree of its shape."""
    scaled = ConeState(**{f.name: jnp.full_like(getattr(y, f.name), SCALES[f.name])
                          for f in dataclasses.fields(ConeState)})
    return scaled, jnp.full_like(e_pos, SCALES["e_pos"])


def edge_times(loading: Loading, cycles: int) -> np.ndarray:
    """Square-wave edges of every cell over ``cycles`` periods, for ``jump_ts``.

    **Arguments:**

    - `loading`: the cells' loadings (leading axis = cells, concrete).
    - `cycles`: periods from t = 0.

    **Returns:**

    ``(n_cells, n_edges)`` float64: ``(k + e) / f`` for ``k < cycles`` and every distinct
    edge fraction ``e`` of the cell's drive (all membranes), t = 0 left out; rows are padded
    with their last edge to a common length (repeated jump times are harmless).
    """
    frac = np.asarray(jax.vmap(lambda ld: ld.drive.edge_fractions())(loading)) % 1.0
    freq = np.asarray(loading.drive.frequency, dtype=float)
    rows = []
    for fr, f in zip(frac, freq):
        e = np.unique(np.round(fr, 12))
        t = ((np.arange(cycles)[:, None] + e[None, :]).ravel()) / f
        rows.append(np.sort(t[t > 0.0]))
    width = max(r.size for r in rows)
    return np.stack([np.pad(r, (0, width - r.size), mode="edge") for r in rows])


def solve_cells(model: Model, loading: Loading, jumps: jax.Array, *, cycles: int, average: int,
                rtol: float, atol: float, max_steps: int) -> dict[str, jax.Array]:
    """The vmapped solve (jittable): per-cell P_out, P_in, P_in_signed, steps, result code.

    **Arguments:**

    - `model`: the configured cone; its actuator's vector field is the right-hand side.
    - `loading`: the cells' loadings (leading axis = cells).
    - `jumps`: ``(n_cells, n_edges)`` edge times (:func:`edge_times`).
    - `cycles`, `average`: periods run from rest; periods averaged at the end.
    - `rtol`, `atol`: tolerances of the PID controller (``atol`` on the scaled state).
    - `max_steps`: diffrax's step budget per cell.

    **Returns:**

    ``{name: (n_cells,) array}``: P_out, P_in, P_in_signed (W), steps (accepted + rejected),
    ok (diffrax reported success).
    """
    act = model.actuator
    y_rest = act.initial_state()
    z_rest = (y_rest, jnp.zeros(act.n_membranes))
    scale = _scale_tree(*z_rest)

    def rhs(t, z, args):
        y = jax.tree_util.tree_map(jnp.multiply, z[0], scale[0])
        dy = act.vector_field(t, y, args)
        dz = (dy, jnp.maximum(dy.energy_in, 0.0))  # e_pos: input energy without recovery
        return jax.tree_util.tree_map(jnp.divide, dz, scale)

    def one(loading: Loading, jump_ts: jax.Array) -> dict[str, jax.Array]:
        period = 1.0 / loading.drive.frequency
        t1 = cycles * period
        t_win = (cycles - average) * period
        z0 = jax.tree_util.tree_map(jnp.divide, z_rest, scale)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(rhs), diffrax.Tsit5(), t0=0.0, t1=t1, dt0=None, y0=z0,
            args=loading,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, pcoeff=PCOEFF,
                                                      icoeff=ICOEFF, jump_ts=jump_ts),
            saveat=diffrax.SaveAt(ts=jnp.stack([t_win, t1])), max_steps=max_steps,
            throw=False)
        (y, e_pos) = jax.tree_util.tree_map(jnp.multiply, sol.ys, scale)
        span = average * period
        d_in = y.energy_in[1] - y.energy_in[0]
        return dict(P_out=(y.payload_work[1] - y.payload_work[0]) / span,
                    P_in=jnp.sum(e_pos[1] - e_pos[0]) / span,
                    P_in_signed=jnp.sum(d_in) / span,
                    steps=sol.stats["num_steps"],
                    ok=sol.result == diffrax.RESULTS.successful)

    return jax.vmap(one)(loading, jumps)


def diffrax_cells(model: Model, mass, damping, freq, *, drive: str = "A", cycles: int = 100,
                  average: int = 5, rtol: float = RTOL, atol: float | None = None,
                  max_steps: int = 2**20) -> dict:
    """Run the cells with a vmapped ``diffrax.diffeqsolve`` and time it.

    **Arguments:**

    - `model`: a square-wave cone from :func:`jaxdea.load_config`.
    - `mass`, `damping`, `freq`: per-cell payload mass (kg), damping (N s/m), drive frequency
      (Hz): 1-D arrays of equal length (or broadcastable to one).
    - `drive`: ``"A"``, ``"B"`` or ``"both"`` (:func:`jaxdea.make_loadings`).
    - `cycles`, `average`: periods from rest; the last ``average`` are averaged.
    - `rtol`: the PID controller's relative tolerance (default :data:`RTOL`); `atol`: its
      absolute tolerance on the scaled state (default ``rtol``; :data:`SCALES`).
    - `max_steps`: diffrax's step budget per cell.

    **Returns:**

    ``dict`` of numpy arrays ``P_out``, ``P_in``, ``P_in_signed`` (W), ``steps`` (accepted +
    rejected, per cell), ``ok`` (diffrax reported success), and floats ``wall_s`` (the second
    call: compile excluded), ``first_s`` (the first call after compiling), ``compile_s``.
    """
    loading = jaxdea.make_loadings(model, mass, damping, freq, drive=drive)
    jumps = jnp.asarray(edge_times(loading, cycles))
    params, static = eqx.partition(model, eqx.is_array)  # parameters as inputs, like jaxdea's
    fn = jax.jit(lambda p, ld, j: solve_cells(
        eqx.combine(p, static), ld, j, cycles=cycles, average=average, rtol=rtol,
        atol=rtol if atol is None else atol, max_steps=max_steps))
    t0 = time.perf_counter()
    compiled = fn.lower(params, loading, jumps).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(params, loading, jumps))
        times.append(time.perf_counter() - t0)
    res = {k: np.asarray(v) for k, v in out.items()}
    return dict(res, wall_s=times[1], first_s=times[0], compile_s=compile_s)


def quick() -> None:
    """The --quick check: diffrax vs jaxdea vs LSODA on 6 DCDEA-LS cells (module docstring)."""
    sys.path.insert(0, str(ROOT / "tests"))
    import scipy_reference

    n_dev = jaxdea.use_cpu_cores()  # as the benches do: jaxdea's cells split over the cores
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    mass, damping, cycles, average = 2e-3, 0.1, 20, 5
    freq = np.round(np.geomspace(20.0, 200.0, 6), 3)
    n = freq.size

    dfx = diffrax_cells(model, np.full(n, mass), np.full(n, damping), freq, cycles=cycles,
                        average=average)
    kw = dict(mass=mass, damping=damping, freq=freq, drive="A", cycles=cycles, average=average,
              early_exit=None)
    jaxdea.sweep(model, **kw)  # compile (and cache) the engine
    t0 = time.perf_counter()
    ds = jaxdea.sweep(model, **kw)
    jax_s = time.perf_counter() - t0
    jax_steps = ds.steps.values.astype(float)

    errs: dict[str, list[float]] = {"diffrax": [], "jaxdea": []}
    print(f"DCDEA-LS drive A, M {mass * 1e3:g} g, c {damping:g} N s/m, {cycles} cycles, mean "
          f"of the last {average}; diffrax rtol {RTOL:g} (Tsit5, PID {PCOEFF}/{ICOEFF}, "
          f"jump_ts), jaxdea defaults, LSODA rtol 1e-8")
    print(f"{'f Hz':>7} | {'P_out mW: diffrax':>19} {'jaxdea':>10} {'LSODA':>10} | "
          f"{'P_in mW: diffrax':>16} {'jaxdea':>9} {'LSODA':>9} | "
          f"{'rel err: diffrax':>16} {'jaxdea':>7} | {'steps/cycle: diffrax':>20} {'jaxdea':>6}")
    for i, f in enumerate(freq):
        ref = scipy_reference.reference_metrics("dcdea_ls", mass, damping, float(f),
                                                cycles=cycles, average=average, rtol=1e-8)
        row = {}
        for name, p_out, p_in in (("diffrax", dfx["P_out"][i], dfx["P_in"][i]),
                                  ("jaxdea", ds.P_out.values[i], ds.P_in.values[i])):
            row[name] = max(abs(p_out / ref["P_out"] - 1), abs(p_in / ref["P_in"] - 1))
            errs[name].append(row[name])
        print(f"{f:7.2f} | {dfx['P_out'][i] * 1e3:19.6g} {ds.P_out.values[i] * 1e3:10.6g} "
              f"{ref['P_out'] * 1e3:10.6g} | {dfx['P_in'][i] * 1e3:16.4f} "
              f"{ds.P_in.values[i] * 1e3:9.4f} {ref['P_in'] * 1e3:9.4f} | "
              f"{row['diffrax']:16.1e} {row['jaxdea']:7.1e} | "
              f"{dfx['steps'][i] / cycles:20.1f} {jax_steps[i] / cycles:6.1f}", flush=True)
    lanes_dfx = n * dfx["steps"].max()  # a vmapped while loop runs every lane to the longest
    print(f"diffrax (1 device, plain vmap): {dfx['wall_s']:.3f} s (second call; compile "
          f"{dfx['compile_s']:.1f} s, first call {dfx['first_s']:.3f} s), "
          f"{dfx['wall_s'] / dfx['steps'].sum() * 1e9:.0f} ns per step taken, "
          f"{dfx['wall_s'] / lanes_dfx * 1e9:.0f} ns per lane-iteration "
          f"(all {n} lanes x the longest cell's {dfx['steps'].max()} steps); all ok: "
          f"{bool(dfx['ok'].all())}")
    print(f"jaxdea ({n_dev} device(s), early exit off): {jax_s:.3f} s (second call), "
          f"{jax_s / jax_steps.sum() * 1e9:.0f} ns per step taken "
          f"({jax_s * n_dev / jax_steps.sum() * 1e9:.0f} ns per step per device); status ok "
          f"{int((ds.status.values == 0).sum())}/{n}")
    print(f"RESULT diffrax_ratio={dfx['wall_s'] / jax_s:.2f} "
          f"diffrax_err={max(errs['diffrax']):.2e} jaxdea_err={max(errs['jaxdea']):.2e} "
          f"diffrax_s={dfx['wall_s']:.3f} jaxdea_s={jax_s:.3f} "
          f"diffrax_steps={int(dfx['steps'].sum())} jaxdea_steps={int(jax_steps.sum())} "
          f"devices={n_dev}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="6 DCDEA-LS cells, 20 cycles: diffrax vs jaxdea vs LSODA")
    args = ap.parse_args()
    if not args.quick:
        ap.error("only --quick runs standalone; the benches import diffrax_cells")
    quick()


if __name__ == "__main__":
    main()
