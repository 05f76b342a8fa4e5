"""Is the lane engine slower than it was? Two (or more) git revisions timed on one map,
interleaved.

Each revision is checked out in its own temporary ``git worktree`` and imported from there
(``PYTHONPATH=<worktree>/src``, this environment's dependencies). Round by round, each
revision runs the powermap bench's 8 x 8 x 64 DCDEA-LS map (M 0.1-10 g, c 0.1-10 N s/m,
1-200 Hz, 100 cycles with the default early exit, one JAX device per core) in a fresh
process: a same-shape warm-up (compile; a shared on-disk XLA cache makes later rounds
load it), then the timed map, best of two. The figure is ns per lane-step (wall time x
devices / integration steps), so a change of the step count is not read as a change of the
step's cost.

Why interleaved and repeated: this machine's speed drifts by +-20 % from one minute to the
next. One process per revision, once each, measured the first release 1.36x cheaper per
lane-step than HEAD (836 against 612 trajectories/s); six interleaved rounds of the same
two revisions gave medians of 547 and 545 ns (``bench/NOTES.md``).

    python bench/compare_revisions.py eba65d1 HEAD [--rounds 6]

Ends with one line: RESULT key=value ... (each revision's median and min ns per lane-step,
and the last revision's median over the first's).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The child process: imports jaxdea from its worktree, prints one ``RES`` line.
CHILD = r"""
import sys, time
import numpy as np
import jax
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
import jaxdea
n_dev = jaxdea.use_cpu_cores()
model = jaxdea.load_config(sys.argv[2])
mass, damping = np.logspace(-4, -2, 8), np.logspace(-1, 1, 8)
freq = np.round(np.linspace(1.0, 200.0, 64), 6)
kw = dict(mass=mass, damping=damping, freq=freq, drive="A", cycles=100, average=5,
          progress=False)
jaxdea.powermap(model, **{**kw, "mass": mass * 1.05})
best = float("inf")
for _ in range(2):
    t0 = time.perf_counter()
    ds = jaxdea.powermap(model, **kw)
    best = min(best, time.perf_counter() - t0)
steps = int(ds.steps.values.sum())
print(f"RES {best} {steps} {best * n_dev / steps * 1e9} {float(ds.P_out.sum())!r}")
"""


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True,
                          text=True).stdout.strip()


def run_one(tree: Path, cache: Path) -> tuple[float, int, float, float]:
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    out = subprocess.run([sys.executable, "-c", CHILD, str(cache),
                          str(ROOT / "configs" / "dcdea_ls.toml")], cwd=tree, env=env,
                         capture_output=True, text=True)
    line = [x for x in out.stdout.splitlines() if x.startswith("RES ")]
    if out.returncode or not line:
        raise SystemExit(f"revision at {tree} failed:\n{out.stderr[-2000:]}")
    t, steps, ns, p = line[-1].split()[1:]
    return float(t), int(steps), float(ns), float(p)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("revs", nargs="+", help="git revisions (at least two)")
    ap.add_argument("--rounds", type=int, default=6)
    args = ap.parse_args()
    if len(args.revs) < 2 or args.rounds < 1:
        raise SystemExit("need two or more revisions and --rounds >= 1")
    shas = [git("rev-parse", "--short", r) for r in args.revs]
    with tempfile.TemporaryDirectory(prefix="jaxdea-revs-") as tmp:
        trees = {}
        try:  # every worktree added is removed again, even if a later one fails
            for sha in dict.fromkeys(shas):
                git("worktree", "add", "--detach", str(Path(tmp) / sha), sha)
                trees[sha] = Path(tmp) / sha
            ns = {sha: [] for sha in trees}
            for r in range(args.rounds):
                for sha, tree in trees.items():
                    t, steps, per, p = run_one(tree, Path(tmp) / "xla")
                    ns[sha].append(per)
                    print(f"round {r + 1}: {sha}: {t:.2f} s, {steps} steps, {per:.0f} ns per "
                          f"lane-step, sum P_out {p:.9e} W", flush=True)
        finally:
            for tree in trees.values():
                git("worktree", "remove", "--force", str(tree))
    med = {sha: statistics.median(v) for sha, v in ns.items()}
    for sha, v in ns.items():
        print(f"{sha}: median {med[sha]:.0f} ns, min {min(v):.0f}, max {max(v):.0f} "
              f"over {len(v)} rounds")
    first, last = shas[0], shas[-1]
    fields = [f"{s}_median_ns={med[s]:.0f} {s}_min_ns={min(ns[s]):.0f}" for s in trees]
    print("RESULT " + " ".join(fields) + f" ratio_last_over_first={med[last] / med[first]:.3f}")


if __name__ == "__main__":
    main()
