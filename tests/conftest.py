import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

# The suite runs on one JAX CPU device. XLA's Eigen intra-op pool has nothing to split in the
# lane engine's tiny ops, and its spinning workers can take half a core from the compute
# thread (jaxdea.use_cpu_cores sets the same flag for the CLI and benches). Set before JAX
# starts its backend; threading only, the numbers are unchanged.
if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_cpu_multi_thread_eigen=false").strip()

import jaxdea  # noqa: E402

CONFIG_DIR = Path(__file__).parents[1] / "configs"


@pytest.fixture(scope="session")
def models():
    return {name: jaxdea.load_config(CONFIG_DIR / f"{name}.toml")
            for name in ("scdea_ls", "dcdea_rr", "dcdea_ls")}
