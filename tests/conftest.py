import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

import jaxdea  # noqa: E402
from jaxdea.engine.sharding import without_eigen_pool  # noqa: E402

# The suite runs on one JAX CPU device. XLA's Eigen intra-op pool has nothing to split in the
# lane engine's tiny ops, and its spinning workers can take half a core from the compute
# thread (jaxdea.use_cpu_cores does the same for the CLI and benches). Importing jaxdea does
# not start a JAX backend, so this still takes effect; threading only, numbers unchanged.
without_eigen_pool()

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
