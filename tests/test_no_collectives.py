"""Sharded runs compile no collective: the cells dealt over the devices never talk.

Cells are independent, so a run split over several JAX devices needs no cross-device
communication. A collective in any compiled module (e.g. the all-reduce of a gather that
indexes a sharded array with a replicated index) makes every device wait for the others, and
XLA aborts the whole process ("Termination timeout for 'all reduce' ... 40 seconds exceeded")
when one device's thread is that late, as happens on a busy core. This test runs a paper and
a periodic sweep, paper and continuation power maps and a design solve (implicit
gradients, :func:`jaxdea.engine.sensitivity.solve_designs`) on 2 CPU devices in a subprocess that
dumps every optimized HLO module, and checks that none of them contains a collective.
The subprocess has the CLI map's XLA flags, loop hoisting and multi-output fusion included
(the suite runs without them: ``conftest.py``), so it also checks that these programs
compile (XLA's multi-output fusion has aborted on some), really are hoisted, and give this
process's paper sweep.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "dcdea_ls.toml")
SRC = str(ROOT / "src")
COLLECTIVE = re.compile(r"\b(all-reduce|all-gather|all-to-all|collective-permute|"
                        r"reduce-scatter)")
#: A batched LU factorisation: a getrf whose result has a leading batch axis.
BATCHED_LU = re.compile(r"= \(f64\[\d+,\d+,\d+\][^\n]*lapack_dgetrf")

SCRIPT = textwrap.dedent(f"""
    import jax
    import numpy as np

    import jaxdea

    assert len(jax.devices()) == 2, jax.devices()
    model = jaxdea.load_config({CONFIG!r})
    freq = np.array([40.0, 70.0, 100.0])
    short = dict(cycles=6, average=2)
    for protocol in ("paper", "periodic"):
        ds = jaxdea.sweep(model, mass=2e-3, damping=0.1, freq=freq, protocol=protocol,
                          **short)
        print(protocol, "sweep: most cycles", int(ds["cycles_run"].max()))
        print(protocol, "sweep: P_out", repr(ds["P_out"].values.ravel().tolist()))
    for protocol in ("paper", "continuation"):
        ds = jaxdea.powermap(model, mass=[1e-3, 2e-3], damping=[0.1], freq=freq,
                             protocol=protocol, progress=False, **short)
        print(protocol, "map: status", ds["status"].values.ravel().tolist())
    # the design study's solve splits its designs over the devices too
    from jaxdea.engine.sensitivity import Steady, solve_designs
    from jaxdea.studies.design import make_builder

    build = make_builder(model, ["voltage"], [], mass=2e-3, damping=0.1,
                         freq=np.array([60.0, 90.0]), drive="A", phase=None, shift=False)
    r = solve_designs(build, np.array([[4.9e3], [4.7e3]]), devices=tuple(jax.devices()),
                      settings=Steady(tol=1e-6, warmup=6, newton=4))
    print("designs: status", r.status.ravel().tolist())
""")


def test_sharded_runs_compile_no_collective(tmp_path):
    from jaxdea.engine import sharding

    dump = tmp_path / "hlo"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    hoist = sharding.with_extra_option("", sharding.SMALL_WHILE_LOOP_OPTION,
                                        sharding.SMALL_WHILE_LOOP_BYTES)
    hoist = sharding.with_extra_option(hoist, sharding.MULTI_OUTPUT_FUSION, "true")
    env.update(PYTHONPATH=SRC + os.pathsep + env.get("PYTHONPATH", ""),
               XLA_FLAGS=("--xla_force_host_platform_device_count=2 "
                          f"--xla_cpu_multi_thread_eigen=false {hoist} "
                          f"--xla_dump_to={dump} --xla_dump_hlo_as_text"))
    res = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         env=env, timeout=600)
    assert res.returncode == 0, res.stderr
    # the periodic sweep really shot (more than its 12 warm-up cycles)
    assert int(re.search(r"periodic sweep: most cycles (\d+)", res.stdout)[1]) > 12
    assert "designs: status [0, 0, 0, 0]" in res.stdout, res.stdout
    modules = sorted(dump.glob("*after_optimizations.txt"))
    texts = {p.name: p.read_text() for p in modules}
    assert any("num_partitions=2" in t for t in texts.values()), "nothing ran on 2 devices"
    assert any("xla_cpu_small_call" in t for t in texts.values()), "no loop was hoisted"
    # the hoisted two-device sweep gives this (unhoisted, one-device) process's numbers
    import jaxdea

    here = jaxdea.sweep(jaxdea.load_config(CONFIG), mass=2e-3, damping=0.1,
                        freq=[40.0, 70.0, 100.0], protocol="paper", cycles=6, average=2)
    there = ast.literal_eval(re.search(r"paper sweep: P_out (\[.*\])", res.stdout)[1])
    np.testing.assert_allclose(there, here["P_out"].values.ravel(), rtol=1e-9, atol=0)
    found = {name: sorted(set(COLLECTIVE.findall(t))) for name, t in texts.items()}
    found = {name: ops for name, ops in found.items() if ops}
    assert not found, f"collectives in compiled modules: {found}"
    # No batched LAPACK call in a program that runs on both devices: it splits its batch over
    # XLA's intra-op pool from a pool thread, and with one device per core every pool thread
    # waits for the others (the periodic map deadlock, engine.periodic.newton_step). The
    # unbatched 2x2 solve of the static equilibrium runs inline and is harmless.
    lapack = [name for name, t in texts.items()
              if "num_partitions=2" in t and BATCHED_LU.search(t)]
    assert not lapack, f"batched LAPACK calls in sharded modules: {lapack}"


def test_cpu_flags_ask_for_wide_vectors_only_where_the_cpu_has_them(monkeypatch):
    """``cpu_flags`` adds 512-bit vectors on an AVX-512 CPU, nothing on another one, and
    never overrides a width the user set; it lets XLA hoist the engine's while loops into
    single kernels and, when asked, build multi-output fusions, next to the user's own
    backend extra options and never over their own setting of either; and with an older
    jaxlib (not measured) it adds neither."""
    from jaxdea.engine import sharding

    eigen = "--xla_cpu_multi_thread_eigen=false"
    mof = "xla_cpu_use_multi_output_fusion=true"
    hoist = "xla_cpu_small_while_loop_byte_threshold=1000000000"
    for avx512, given, want in [
            (True, "", f"{eigen} --xla_backend_extra_options={hoist} "
                       "--xla_cpu_prefer_vector_width=512"),
            (False, "", f"{eigen} --xla_backend_extra_options={hoist}"),
            (True, "--xla_cpu_prefer_vector_width=256",
             f"--xla_cpu_prefer_vector_width=256 {eigen} --xla_backend_extra_options={hoist}"),
            (False, "--xla_backend_extra_options=xla_cpu_use_acl=true",
             f"--xla_backend_extra_options=xla_cpu_use_acl=true,{hoist} {eigen}"),
            (False, "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0",
             f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0 {eigen}")]:
        monkeypatch.setenv("XLA_FLAGS", given)
        monkeypatch.setattr(sharding, "host_has_avx512", lambda avx512=avx512: avx512)
        monkeypatch.setattr(sharding, "_jaxlib_version", lambda: (0, 10))
        sharding.cpu_flags()
        assert os.environ["XLA_FLAGS"] == want
    # multi-output fusion only when asked for (the CLI's sweep and powermap); the user's
    # "=false" keeps it off, and is removed (XLA turns the option on by its presence)
    for given, fuse, want in [
            ("", True, f"{eigen} --xla_backend_extra_options={hoist},{mof}"),
            (f"--xla_backend_extra_options={mof}", False,
             f"--xla_backend_extra_options={mof},{hoist} {eigen}"),
            ("--xla_backend_extra_options=xla_cpu_use_multi_output_fusion=false", True,
             f"--xla_backend_extra_options={hoist} {eigen}")]:
        monkeypatch.setenv("XLA_FLAGS", given)
        sharding.cpu_flags(fuse_outputs=fuse)
        assert os.environ["XLA_FLAGS"] == want
    assert sharding.without_extra_option(
        f"--a=1 --xla_backend_extra_options={mof} --b=2", sharding.MULTI_OUTPUT_FUSION) == (
        "--a=1 --b=2")
    assert sharding.without_extra_option(
        f"--xla_backend_extra_options={hoist},{mof}", sharding.MULTI_OUTPUT_FUSION) == (
        f"--xla_backend_extra_options={hoist}")
    monkeypatch.setenv("XLA_FLAGS", "")
    sharding.cpu_flags(hoist_loops=False)  # the test suite's flags: no loop hoisted, said so
    assert os.environ["XLA_FLAGS"] == (
        f"{eigen} --xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0")
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(sharding, "_jaxlib_version", lambda: (0, 9))  # flags not measured there
    sharding.cpu_flags(fuse_outputs=True)
    assert os.environ["XLA_FLAGS"] == eigen


def test_scatter_each_is_a_scatter_in_value_and_both_derivative_modes():
    """``lane_state.scatter_each`` (the engine's scatters, kept apart for XLA's multi-output
    fusion) writes what ``.at[index].set`` writes, dropping out-of-bound rows, and its
    derivatives forward and reverse are that scatter's."""
    import jax
    import jax.numpy as jnp

    from jaxdea.engine.lane_state import scatter_each

    index = jnp.array([1, 4, 4, 2])  # 4 is out of bounds: dropped (and repeated)

    def mine(x):
        out = (jnp.zeros(4), jnp.ones(4, jnp.int32))
        y, k = scatter_each(out, index, (x * x, jnp.array([3, 5, 5, 2], jnp.int32)))
        return y * k

    def plain(x):
        k = jnp.ones(4, jnp.int32).at[index].set(jnp.array([3, 5, 5, 2], jnp.int32), mode="drop")
        return jnp.zeros(4).at[index].set(x * x, mode="drop") * k

    x = jnp.array([1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(mine(x), plain(x))
    np.testing.assert_array_equal(mine(x), [0.0, 3.0, 32.0, 0.0])
    for mode in (jax.jacfwd, jax.jacrev):
        np.testing.assert_array_equal(mode(mine)(x), mode(plain)(x))
    assert float(jax.jacrev(mine)(x)[2, 3]) == 16.0  # row 2 is 2 x[3]^2
