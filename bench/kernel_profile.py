"""The lane step kernel by kernel: time per call, size, and whether LLVM vectorised it.

Issue 16, item 1 ("time per op"). Workload: DCDEA-LS, drive A, 128 cells per device (a 16 x 8
payload grid per device, M 0.1-10 g, c 0.1-10 N s/m) at 60 Hz, 20 cycles without the early
exit (every lane busy), through ``jaxdea.powermap`` on ``--devices`` CPU devices. The map is
run once to compile, then once under ``jax.profiler`` with XLA's per-kernel trace events on
(``--xla_cpu_enable_xprof_traceme``), and XLA dumps every kernel's optimised LLVM IR
(``--xla_dump_to``, a temporary directory).

For each kernel of the step's loop body (the computation with the most fusions): ns per
call (its calls are the lane steps of one device), its HLO operations (parameters,
constants, broadcasts and tuples not counted) and whether its IR has vector instructions
(``<N x double>``). The trace's own cost is ~1 us per kernel on this machine's 2 cores, so
the times rank kernels, they do not add up to an untraced step (``bench/lane_profile.py``
measures that).

What it found (2026-12-06): on one device, the two costliest kernels of the step were
scalar loops, one of them calling a non-inlined function per element (the stack of the two
disks' accelerations: fixed in ``DCDEA_LS.accelerations``); on two devices the same step
compiles to vectorised kernels.

    python bench/kernel_profile.py [--devices 1] [--top 15]

Ends with one line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: HLO operations that are not work (not counted as a kernel's size).
FREE = ("parameter", "constant", "broadcast", "bitcast", "tuple", "get-tuple-element")


def computations(hlo: str) -> dict[str, str]:
    """An HLO module's text split into its computations, by name."""
    blocks = re.split(r"\n(?=(?:%|ENTRY )\S* \(.*\{\s*$)", hlo, flags=re.M)
    return {b.split("\n", 1)[0].split(" ")[0].lstrip("%"): b for b in blocks}


def step_kernels(hlo: str) -> dict[str, tuple[str, int]]:
    """The step's loop body (the non-fused computation with the most fusions): each fusion's
    output shape and size in HLO operations."""
    comp = computations(hlo)
    body = max((b for n, b in comp.items() if not n.startswith("fused")),
               key=lambda b: len(re.findall(r" fusion\(", b)))
    out = {}
    for line in body.split("\n"):
        m = re.match(r"\s+%(\S+) = (\S+?)(?:\{[^}]*\})? fusion\(.*?calls=%(\S+?),", line)
        if m:
            ops = collections.Counter(re.findall(r"= \S+ (\w[\w-]*)\(", comp[m.group(3)]))
            out[m.group(1)] = (m.group(2), sum(v for k, v in ops.items() if k not in FREE))
    return out


def vectorised(dump: str) -> dict[str, bool]:
    """Kernel name -> whether its optimised LLVM IR has vector instructions (the module with
    the most kernels in the dump)."""
    files = glob.glob(os.path.join(dump, "*_kernel_module.ir-with-opt.ll"))
    prefix = collections.Counter(".".join(os.path.basename(f).split(".")[:2]) for f in files)
    top = prefix.most_common(1)[0][0]
    out = {}
    for f in files:
        base = os.path.basename(f)
        if base.startswith(top + "."):
            name = base[len(top) + 1:-len("_kernel_module.ir-with-opt.ll")]
            out[name] = re.search(r"<\d+ x double>", Path(f).read_text()) is not None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=1, help="CPU devices (default 1)")
    ap.add_argument("--top", type=int, default=15, help="kernels listed (default 15)")
    args = ap.parse_args()
    if args.devices < 1:
        raise SystemExit(f"--devices must be >= 1, got {args.devices}")
    dump = tempfile.mkdtemp(prefix="jaxdea_kernels_")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_cpu_enable_xprof_traceme=true --xla_dump_to={dump}")
    import jax
    import numpy as np
    from jax._src import compiler

    import jaxdea

    n_dev = jaxdea.use_cpu_cores(args.devices)
    hlos = []
    compile_ = compiler.compile_or_get_cached

    def keep_hlo(backend, computation, *a, **k):
        executable = compile_(backend, computation, *a, **k)
        try:
            hlos.append(executable.hlo_modules()[0].to_string())
        except Exception:  # an executable without HLO text: not the engine's
            pass
        return executable

    compiler.compile_or_get_cached = keep_hlo
    model = jaxdea.load_config(ROOT / "configs" / "dcdea_ls.toml")
    kw = dict(mass=np.logspace(-4, -2, 16 * n_dev), damping=np.logspace(-1, 1, 8),
              freq=np.array([60.0]), drive="A", cycles=20, average=2, early_exit=None,
              progress=False)
    jaxdea.powermap(model, **kw)
    compiler.compile_or_get_cached = compile_
    kernels = step_kernels(max(hlos, key=len))
    vec = vectorised(dump)
    trace = os.path.join(dump, "trace")
    jax.profiler.start_trace(trace)
    t0 = time.perf_counter()
    ds = jaxdea.powermap(model, **kw)
    wall = time.perf_counter() - t0
    jax.profiler.stop_trace()
    steps = float(ds.steps.sum())
    data = jax.profiler.ProfileData.from_file(
        glob.glob(os.path.join(trace, "**", "*.xplane.pb"), recursive=True)[0])
    total, calls = collections.Counter(), collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            for ev in line.events:
                if ev.name in kernels:
                    total[ev.name] += ev.duration_ns
                    calls[ev.name] += 1
    per_call = {k: total[k] / calls[k] for k in total}
    traced = sum(per_call.values())
    print(f"{n_dev} device(s), {len(kernels)} kernels in the step's loop body, "
          f"{len(per_call)} traced; traced run {wall:.2f} s for {steps:.3g} lane-steps "
          f"({wall / steps * 1e9 * n_dev:.0f} ns per device lane-step with the trace on)")
    print(f"{'ns/call':>8} {'share':>6} {'ops':>5} {'vector':>6}  kernel (output shape)")
    for name, ns in sorted(per_call.items(), key=lambda kv: -kv[1])[:args.top]:
        shape, ops = kernels[name]
        print(f"{ns:8.0f} {100 * ns / traced:5.1f}% {ops:5d} {str(vec.get(name, '?')):>6}  "
              f"{name} ({shape})")
    scalar = [k for k in per_call if vec.get(k) is False and kernels[k][1] > 20]
    scalar_ns = sum(per_call[k] for k in scalar)
    top = max(per_call, key=per_call.get)
    print(f"scalar kernels of more than 20 operations: {len(scalar)}, "
          f"{100 * scalar_ns / traced:.0f} % of the traced kernel time")
    print("RESULT " + " ".join([
        f"devices={n_dev}", f"kernels={len(kernels)}", f"traced_kernels={len(per_call)}",
        f"traced_step_us={traced / 1e3:.1f}", f"top_kernel={top}",
        f"top_kernel_ns={per_call[top]:.0f}", f"scalar_kernels={len(scalar)}",
        f"scalar_share={scalar_ns / traced:.3f}"]))


if __name__ == "__main__":
    sys.exit(main())
