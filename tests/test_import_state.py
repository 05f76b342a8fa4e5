"""Importing jaxdea switches on float64 and changes no other global state (jaxdea/__init__.py
says why float64): no other JAX config value, no environment variable, no started backend
(so :func:`jaxdea.use_cpu_cores` can still set the device count)."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = r"""
import json, os
import jax
from jax._src import xla_bridge
before = {k: repr(v) for k, v in jax.config.values.items()}
env = dict(os.environ)
import jaxdea  # noqa: F401
after = {k: repr(v) for k, v in jax.config.values.items()}
print(json.dumps({
    "config": sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k)),
    "env": sorted(k for k in set(env) | set(os.environ) if env.get(k) != os.environ.get(k)),
    "backend_started": xla_bridge.backends_are_initialized(),
    "x64": bool(jax.config.jax_enable_x64),
}))
"""


def test_import_changes_only_float64():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         check=True)
    state = json.loads(out.stdout.strip().splitlines()[-1])
    assert state["config"] == ["jax_enable_x64"]
    assert state["x64"] is True
    assert state["env"] == []
    assert state["backend_started"] is False
