import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

import jaxdea  # noqa: E402

CONFIG_DIR = Path(__file__).parents[1] / "configs"


@pytest.fixture(scope="session")
def models():
    return {name: jaxdea.load_config(CONFIG_DIR / f"{name}.toml")
            for name in ("scdea_ls", "dcdea_rr", "dcdea_ls")}
