import collections
import getpass
import os
import sys
import tempfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

import jax  # noqa: E402

import jaxdea  # noqa: E402
from jaxdea.engine.sharding import cpu_flags  # noqa: E402

# The suite runs on one JAX CPU device, with the engine's XLA CPU flags (as jaxdea.use_cpu_cores
# sets them for the CLI and benches): no Eigen intra-op pool (it has nothing to split in the
# lane engine's tiny ops, and its spinning workers can take half a core from the compute
# thread), and 512-bit vectors where the CPU has AVX-512. Importing jaxdea does not start a
# JAX backend, so this still takes effect. The wide vectors move a warm-started map's results by
# ~1e-10 at most (bench/NOTES.md), far inside every tolerance here. Multi-output fusion (the
# CLI's sweep and powermap only) is left out: XLA aborts on some programs the suite compiles
# (diffrax's saving under vmap); test_no_collectives compiles the engine with it. The other
# flag left out is the loop hoisting (every while loop one kernel): it makes maps on two
# devices ~0.8x faster but one device's forward-mode shoots compile up to 2.6x slower, and
# the suite is compile-bound. It is written out as off (threshold 0), so that CLI runs
# started from here inherit it and write maps equal to this process's to the last bit;
# test_no_collectives runs the CLI's flags, hoisting included, in a subprocess and checks its
# sweep against this one's.
cpu_flags(hoist_loops=False)

# Compiled programs go to an on-disk cache shared by the pytest workers: many modules compile
# the same engines (same config, protocol and shape), and the module-end cache release below
# would otherwise compile them again; a hit loads the executable instead. The cache is keyed
# by the program and the compiler's options, so a stale entry is never used.
_XLA_CACHE = Path(tempfile.gettempdir()) / f"jaxdea-tests-xla-cache-{getpass.getuser()}"
jax.config.update("jax_compilation_cache_dir", str(_XLA_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
# and a `jaxdea` command started by a test uses the same cache, not the user's home directory
os.environ.setdefault("JAXDEA_COMPILE_CACHE", str(_XLA_CACHE))

CONFIG_DIR = Path(__file__).parents[1] / "configs"


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module: the suite compiles hundreds of
    engines (every config, protocol, shape), and keeping them all grew one process past
    several GiB and once crashed XLA's compiler late in the run."""
    yield
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


@pytest.fixture(scope="session")
def models():
    return {name: jaxdea.load_config(CONFIG_DIR / f"{name}.toml")
            for name in ("scdea_ls", "dcdea_rr", "dcdea_ls")}


#: Modules whose tests run on any worker, one by one: each compiles its own programs (a
#: notebook per subprocess, a configuration per gradient check), so keeping them together
#: saves nothing and puts minutes of work on one worker. They are queued first (the longest
#: work first keeps the two workers' finishing times close).
SPREAD = ("test_design_gradients.py", "test_notebooks.py", "test_paper000.py")


def _module(nodeid: str) -> str:
    return nodeid.split("::")[0]


def pytest_collection_modifyitems(config, items):
    """The tests of :data:`SPREAD` first, then the other modules, most tests first (as
    xdist's default order of modules; the scheduler below keeps this order)."""
    count = collections.Counter(_module(item.nodeid) for item in items)
    items.sort(key=lambda item: (Path(_module(item.nodeid)).name not in SPREAD,
                                 -count[_module(item.nodeid)]))


def pytest_xdist_make_scheduler(config, log):
    """xdist's ``--dist loadfile`` (a module's tests share its fixtures and compiled programs
    on one worker), except that each test of :data:`SPREAD` is a unit of its own."""
    from xdist.scheduler import LoadFileScheduling

    class Scheduling(LoadFileScheduling):
        def __init__(self, config, log=None):
            super().__init__(config, log)
            config.option.loadscopereorder = False  # by test count it put SPREAD last

        def _split_scope(self, nodeid: str) -> str:
            module = _module(nodeid)
            return nodeid if Path(module).name in SPREAD else module

    return Scheduling(config, log)
