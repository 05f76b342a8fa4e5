"""Run a per-cell function with its cells split evenly over several JAX devices.

Every protocol stage (:func:`jaxdea.engine.lanes.run_protocol`, the shooting step of
:mod:`jaxdea.engine.periodic`) maps independent cells to per-cell results, so it shards trivially:
``jax.shard_map`` over a 1-D mesh, the model replicated, every other argument and every output
split along its leading (cell) axis. Each device then runs its own lane pool on its slice.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def cell_sharded(fn: Callable, devices: tuple) -> Callable:
    """``fn(model, *cell_args, **static)`` run as ``shard_map`` over ``devices`` (jitted,
    cached per ``fn`` and device set). Cell arguments are pytrees whose leaves all have the
    cell axis first, with a length divisible by ``len(devices)``; ``static`` keyword
    arguments are compile-time constants. Index-valued cell arguments (e.g. successors) must
    be local to each device's slice.

    The results come back as numpy arrays on the host (:func:`to_host`), never as arrays
    sharded over the devices: cells are independent, so no step of a sharded run may need a
    collective, and any later jnp operation that mixed a sharded array with an unsharded one
    (indexing with a numpy index, ``jnp.where`` on a mask) would compile to an all-reduce
    that XLA aborts the process on when one device's thread is 40 s late (a busy core)."""
    return _sharded(fn, tuple(devices))


@functools.cache
def _cell_mesh(devices: tuple) -> Mesh:
    """The one-axis mesh ("cells") of ``devices`` that sharded runs split their cells over."""
    return Mesh(np.array(devices), ("cells",))


@functools.cache
def _sharded(fn: Callable, devices: tuple) -> Callable:
    """The jitted ``shard_map`` of ``fn`` over ``devices``, built once per pair."""
    mesh = _cell_mesh(devices)

    def run(model, *cells, **static):
        dyn, const = eqx.partition(model, eqx.is_array)

        def body(dyn, *cells):
            return fn(eqx.combine(dyn, const), *cells, **static)

        # check_vma off: the lane engine's while_loop carry starts from replicated values
        # (the model's rest state) that become device-varying, which the vma check rejects
        spec = PartitionSpec("cells")
        return jax.shard_map(body, mesh=mesh, in_specs=(PartitionSpec(),) + (spec,) * len(
            cells), out_specs=spec, check_vma=False)(dyn, *cells)

    jitted = eqx.filter_jit(run)
    return lambda *args, **kwargs: to_host(jitted(*args, **kwargs))


def replicated(tree, devices: tuple):
    """``tree`` with its arrays copied once onto every one of ``devices`` (as
    :func:`cell_sharded` runs take a model): a model passed to many sharded calls, e.g. by
    the warm-start chain's hundreds of one-period calls, is then not copied to the devices
    on every call. Unchanged on one device.

    **Arguments:**

    - `tree`: a pytree (e.g. a model); its non-array leaves are kept as they are.
    - `devices`: the devices of the sharded calls it will be passed to.

    **Returns:**

    The same pytree, its arrays replicated over ``devices``.
    """
    if len(devices) < 2:
        return tree
    where = NamedSharding(_cell_mesh(tuple(devices)), PartitionSpec())
    dyn, const = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.device_put(dyn, where), const)


def on_accelerator(devices: tuple = ()) -> bool:
    """Whether ``devices`` (default: JAX's default devices) are accelerators (GPU, TPU), not
    host CPU devices.

    The lane engine's defaults differ there: a CPU device runs a step's few hundred small
    kernels one after another on one core, so a step's cost grows with the pool's width and
    pools stay narrow (:func:`jaxdea.engine.batch.default_lanes`); an accelerator launches
    the same kernels over all lanes at once, so up to a few thousand lanes a step costs its
    launches whatever the width, and the widest pool is the cheapest per cell (beyond that a
    step is bound by memory traffic, so very wide pools shrink as their cells finish:
    :data:`jaxdea.engine.lanes.CASCADE_FROM`).

    **Arguments:**

    - `devices`: JAX devices (default: ``jax.devices()``).

    **Returns:**

    True when any of them is not a CPU device.
    """
    return any(d.platform != "cpu" for d in (tuple(devices) or jax.devices()))


def to_host(tree):
    """The arrays of ``tree`` as numpy arrays on the host (other leaves unchanged).

    Copies each device's shard of a sharded array to the host without a collective
    (``jax.device_get``), unlike indexing or reducing it on the devices."""
    return jax.device_get(tree)


def without_eigen_pool() -> None:
    """Add ``--xla_cpu_multi_thread_eigen=false`` to ``XLA_FLAGS`` unless that flag is set
    (see :func:`use_cpu_cores`; XLA reads it when the backend starts, so call this first)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()


#: XLA's preferred SIMD width (bits) on CPUs with AVX-512 (:func:`cpu_flags`). XLA's default
#: is 256; at 512 the papers' protocol took 0.83 of the time on this project's Xeons with the
#: same results bit for bit, and a warm-started map the same steps and statuses with P_out
#: within 1.4e-10 (``bench/NOTES.md``).
AVX512_VECTOR_WIDTH = 512


def host_has_avx512() -> bool:
    """Whether this machine's CPU reports AVX-512 (``avx512f`` in ``/proc/cpuinfo``; False
    where that file does not exist, as off Linux)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return any(line.startswith("flags") and " avx512f" in line for line in text.splitlines())


def _jaxlib_version() -> tuple[int, int]:
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (PackageNotFoundError, ValueError):
        return (0, 0)


#: XLA's CPU backend runs a while loop whose HLO cost analysis reads fewer bytes than this
#: as one compiled kernel (its ``SmallWhileLoopHoistingPass``, set by a backend extra
#: option; measured with jaxlib 0.10); below it (XLA's default is ~1 kB, which no engine
#: loop is) a loop runs one runtime call (thunk) per fused kernel per step (~160 a
#: lane-step). 1e9 lets every loop of the engine through (a loop with a host callback or a
#: collective never is: XLA checks). Measured: ``bench/NOTES.md``.
SMALL_WHILE_LOOP_BYTES = 1_000_000_000
#: The backend extra option that sets it (:data:`SMALL_WHILE_LOOP_BYTES`).
SMALL_WHILE_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: The backend extra option that lets XLA's CPU fusion build multi-output fusions (off by
#: default in jaxlib 0.10): one kernel computes several values from shared inputs, where
#: single-output fusion copies a shared producer into every consumer (the lane step's fused
#: operations were about twice its HLO operations). Measured with jaxlib 0.10.2: the copied
#: lane step 0.72x the time on one device, the slice's 25 000-cell maps on two devices
#: 0.89x (papers' protocol) and 0.76x (warm-started), compiles no slower
#: (``bench/NOTES.md``). But its emitter aborts the process (a failed check in XLA's
#: ``symbolic_map.cc``) on two scatters of one index merged into one kernel: the engine
#: writes its scatters with :func:`~jaxdea.engine.lane_state.scatter_each`, which avoids
#: that, but diffrax's ``diffeqsolve`` saving under ``vmap`` (the viscoelastic models'
#: transients) and any user program may have them. Hence only the runs that compile the
#: lane engine alone ask for it: ``use_cpu_cores(fuse_outputs=True)`` in the CLI's
#: ``sweep`` and ``powermap`` and in the map benches.
MULTI_OUTPUT_FUSION = "xla_cpu_use_multi_output_fusion"


def with_extra_option(flags: str, key: str, value) -> str:
    """An ``XLA_FLAGS`` string with one more XLA backend extra option.

    **Arguments:**

    - `flags`: the ``XLA_FLAGS`` string.
    - `key`, `value`: the option (e.g. :data:`SMALL_WHILE_LOOP_OPTION` and a byte count).

    **Returns:**

    ``flags`` with ``key=value`` appended to its ``--xla_backend_extra_options`` (or as a
    new such flag); ``flags`` itself where ``key`` is in it already (the user's choice)."""
    if key in flags:
        return flags
    words = flags.split()
    for i, word in enumerate(words):
        if word.startswith("--xla_backend_extra_options="):
            words[i] = f"{word},{key}={value}"
            return " ".join(words)
    return (flags + f" --xla_backend_extra_options={key}={value}").strip()


def without_extra_option(flags: str, key: str) -> str:
    """An ``XLA_FLAGS`` string without the XLA backend extra option ``key`` (whatever its
    value: XLA turns some options on by their presence alone, ``key=false`` included), and
    without an ``--xla_backend_extra_options`` left empty.

    **Arguments:**

    - `flags`: the ``XLA_FLAGS`` string.
    - `key`: the option's name (e.g. :data:`MULTI_OUTPUT_FUSION`).

    **Returns:**

    ``flags`` without that option."""
    words = []
    for word in flags.split():
        if word.startswith("--xla_backend_extra_options="):
            kept = [o for o in word.split("=", 1)[1].split(",")
                    if o and o.split("=", 1)[0] != key]
            if not kept:
                continue
            word = "--xla_backend_extra_options=" + ",".join(kept)
        words.append(word)
    return " ".join(words)


def cpu_flags(hoist_loops: bool = True, fuse_outputs: bool = False) -> None:
    """Add the lane engine's XLA CPU flags to ``XLA_FLAGS``, each unless it is set already
    (XLA reads them when the backend starts, so call this first; :func:`use_cpu_cores` does):

    - no Eigen intra-op pool (:func:`without_eigen_pool`);
    - with ``hoist_loops`` and jaxlib 0.10 or newer (the versions this was measured with):
      ``xla_cpu_small_while_loop_byte_threshold`` (:data:`SMALL_WHILE_LOOP_BYTES`) among the
      backend extra options, so that XLA compiles each of the engine's while loops into one
      kernel instead of running its fused kernels (~160 per step) one runtime call at a time.
      On two devices a map's lane steps take ~0.8x the time; on one device the forward-mode
      shoots (periodic protocol, design gradients) compile up to 2.6x slower, hence the
      test suite (compile-bound, one device per worker) turns it off. Off, the threshold is
      written out as 0 (no loop hoisted), so that a process started with these
      ``XLA_FLAGS`` (a CLI run from the suite) compiles as its parent, to the last bit;
    - with ``fuse_outputs`` and jaxlib 0.10 or newer, multi-output fusion
      (:data:`MULTI_OUTPUT_FUSION`, a backend extra option): the lane step ~0.7x the time,
      a map 0.75-0.9x; only for processes that compile the lane engine alone (XLA aborts
      on some other programs: see there);
    - ``--xla_cpu_prefer_vector_width=512`` where the CPU has AVX-512
      (:func:`host_has_avx512`) and jaxlib is 0.10 or newer (XLA stops at an unknown flag).
      The engine's kernels are short elementwise loops over the lanes, which 512-bit
      vectors run in half the instructions (:data:`AVX512_VECTOR_WIDTH`).

    All three change rounding only: multi-output fusion moved a 25 000-cell map's sum of
    P_out by 6e-12 (relative); the wide vectors gave the papers' protocol the same numbers
    bit for bit and a warm-started map P_out within 1.4e-10; with the hoisted loops ten
    engine calls' 34 float64 outputs moved by at most 4e-13 (relative) and a 25 000-cell
    map kept its steady cells, its sum of P_out to 4e-13 and its steps to 0.05 %
    (``bench/NOTES.md``).

    **Arguments:**

    - `hoist_loops`: whether to let XLA compile every while loop into one kernel (else
      none).
    - `fuse_outputs`: whether to ask for multi-output fusion (else it is left as it is).
      ``xla_cpu_use_multi_output_fusion=false`` among the user's backend extra options
      keeps it off: XLA turns it on by the option's presence, so that one is removed.
    """
    without_eigen_pool()
    flags = os.environ.get("XLA_FLAGS", "")
    measured = _jaxlib_version() >= (0, 10)  # the versions these flags were measured with
    if measured:
        flags = with_extra_option(flags, SMALL_WHILE_LOOP_OPTION,
                                  SMALL_WHILE_LOOP_BYTES if hoist_loops else 0)
        if fuse_outputs:
            flags = with_extra_option(flags, MULTI_OUTPUT_FUSION, "true")
    if f"{MULTI_OUTPUT_FUSION}=false" in flags:  # the user's "no": XLA reads presence only
        flags = without_extra_option(flags, MULTI_OUTPUT_FUSION)
    if measured and "xla_cpu_prefer_vector_width" not in flags and host_has_avx512():
        flags = (flags + f" --xla_cpu_prefer_vector_width={AVX512_VECTOR_WIDTH}").strip()
    os.environ["XLA_FLAGS"] = flags


def use_cpu_cores(n: int | None = None, fuse_outputs: bool = False) -> int:
    """Make the CPU backend expose ``n`` devices (default: one per core) and return the count.

    XLA runs a single CPU device's batched elementwise work on one core; with one device per
    core, :func:`cell_sharded` (hence sweeps, power maps and periodic stages) runs a slice of
    the cells on every core. It also turns off XLA's Eigen intra-op thread pool
    (``--xla_cpu_multi_thread_eigen=false``): the lane engine's ops are far too small to
    split, and the pool's spinning workers can take half of a core from a single device's
    compute thread (measured: ``bench/NOTES.md``); it lets XLA compile each of the engine's
    while loops into one kernel, and on CPUs with AVX-512 asks XLA for 512-bit vectors
    (:func:`cpu_flags`). Call it before JAX computes anything
    (the CLI does this at start); afterwards, or when ``XLA_FLAGS`` already sets
    ``--xla_force_host_platform_device_count``, the device count stays as it is.

    **Arguments:**

    - `n`: the number of CPU devices (default: ``os.cpu_count()``).
    - `fuse_outputs`: also ask XLA for multi-output fusion (:data:`MULTI_OUTPUT_FUSION`): a
      map 0.75-0.9x the time, but XLA aborts the process compiling some other programs
      (diffrax's saving under ``vmap``, for one), so only for a process that runs sweeps and
      power maps alone (the CLI's ``sweep`` and ``powermap`` do).

    **Returns:**

    The CPU device count in effect.
    """
    n = int(n or os.cpu_count() or 1)
    cpu_flags(fuse_outputs=fuse_outputs)
    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        try:
            jax.config.update("jax_num_cpu_devices", n)
        except RuntimeError:  # a backend has started: too late, keep what it has
            pass
    return len(jax.devices("cpu"))


#: Environment variable naming the directory of the CLI's on-disk cache of compiled programs
#: (:func:`use_compile_cache`); ``off`` (or ``0``, ``none``, empty) turns the cache off.
COMPILE_CACHE_ENV = "JAXDEA_COMPILE_CACHE"
#: Programs that compile faster than this (s) are not worth a file: the engine's programs
#: take 4-7 s each on 2 cores, helpers well under a second.
COMPILE_CACHE_MIN_SECONDS = 1.0


def default_compile_cache() -> Path | None:
    """The directory :func:`use_compile_cache` uses by default: ``$JAXDEA_COMPILE_CACHE``,
    else ``$XDG_CACHE_HOME/jaxdea/xla`` (``~/.cache/jaxdea/xla``); None when that variable
    says ``off``."""
    text = os.environ.get(COMPILE_CACHE_ENV)
    if text is not None:
        return None if text.strip().lower() in ("", "0", "off", "none") else Path(text)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxdea" / "xla"


def use_compile_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep XLA's compiled programs on disk, so that the next run with the same program
    shapes (the same grid, say, with another spring or prestretch: parameter values are
    arguments, not constants) skips their compile. The CLI calls this at start.

    A cold warm-started map of 125 000 cells spends ~16 s of its ~40 s compiling its three
    engine programs, and the README's small map ~4 s of ~11; a second run loads them
    (``bench/NOTES.md``). Results are the same bit for bit: the programs are the same.
    A directory JAX already uses (set by the caller or ``JAX_COMPILATION_CACHE_DIR``) is
    kept as it is.

    **Arguments:**

    - `path`: the cache directory (created if missing); default
      :func:`default_compile_cache`.

    **Returns:**

    The directory in use, or None where the cache is off or the directory cannot be
    created (the run goes on, compiling as usual).
    """
    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    where = Path(path) if path is not None else default_compile_cache()
    if where is None:
        return None
    try:
        where.mkdir(parents=True, exist_ok=True)
        if not os.access(where, os.W_OK):
            return None
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", COMPILE_CACHE_MIN_SECONDS)
    return where
