"""The CLI's on-disk cache of compiled programs (:func:`jaxdea.use_compile_cache`): where it
lives, how it is turned off, that a broken location never stops a run, and that a rerun
loads the programs (no new entries) and gives the same numbers bit for bit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import xarray as xr

CONFIG = str(Path(__file__).parents[1] / "configs" / "scdea_ls.toml")

PROBE = r"""
import json, jax, jaxdea
where = jaxdea.use_compile_cache()
print(json.dumps({"where": None if where is None else str(where),
                  "jax": jax.config.jax_compilation_cache_dir}))
"""


def _env(**extra):
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXDEA_COMPILE_CACHE", "XDG_CACHE_HOME")}
    return {**env, **extra}


def _probe(**extra) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         check=True, env=_env(**extra))
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_cache_location_off_switch_and_broken_location(tmp_path):
    got = _probe(XDG_CACHE_HOME=str(tmp_path / "xdg"))
    assert got["where"] == got["jax"] == str(tmp_path / "xdg" / "jaxdea" / "xla")
    assert (tmp_path / "xdg" / "jaxdea" / "xla").is_dir()
    got = _probe(JAXDEA_COMPILE_CACHE=str(tmp_path / "mine"))
    assert got["where"] == got["jax"] == str(tmp_path / "mine")
    for off in ("off", "0", ""):
        assert _probe(JAXDEA_COMPILE_CACHE=off) == {"where": None, "jax": None}
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    assert _probe(JAXDEA_COMPILE_CACHE=str(blocker / "xla")) == {"where": None, "jax": None}
    # a cache JAX was told about already is kept
    got = _probe(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jaxs"),
                 JAXDEA_COMPILE_CACHE=str(tmp_path / "mine2"))
    assert got["where"] == got["jax"] == str(tmp_path / "jaxs")
    assert not (tmp_path / "mine2").exists()


def test_cli_rerun_loads_its_programs_and_gives_the_same_numbers(tmp_path):
    cache = tmp_path / "cache"
    outs = []
    for run in range(2):
        out = tmp_path / f"s{run}.nc"
        subprocess.run([sys.executable, "-m", "jaxdea.cli", "sweep", CONFIG, "--mass", "2e-3",
                        "--damping", "0.1", "--freq", "80:90:5", "--cycles", "20",
                        "--average", "5", "--out", str(out)],
                       check=True, capture_output=True, env=_env(JAXDEA_COMPILE_CACHE=str(cache)))
        entries = sorted(p.name for p in cache.iterdir())
        outs.append((entries, xr.load_dataset(out, engine="h5netcdf")))
    (first, a), (second, b) = outs
    assert first, "the first run wrote no compiled program"
    assert second == first  # the rerun compiled nothing new: it loaded them
    for name in ("P_out", "P_in", "amplitude", "steps"):
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
