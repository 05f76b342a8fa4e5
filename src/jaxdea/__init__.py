"""jaxdea: batched, differentiable JAX simulator of cone dielectric elastomer actuators.

Public API (everything else may change):

- :func:`load_config` -> :class:`Model` (validated TOML config, SI units)
- :func:`sweep` -> ``xarray.Dataset`` over frequency (paper 000 protocol)
- :func:`powermap` -> ``xarray.Dataset`` over payload mass x damping x frequency (x phase):
  chunked, sharded over all JAX devices, resumable from a Zarr/NetCDF store
- :func:`simulate` -> trajectory of one drive case (diffrax)
- building blocks: :class:`GentMaxwell`, :class:`ConeMembrane`, :class:`SCDEA_LS`,
  :class:`DCDEA_RR`, :class:`DCDEA_LS`, :class:`SquareWave`, :class:`LinearViscous`,
  :class:`LawsonRK4`, :func:`run_protocol`, :class:`StepControl`.

float64 is switched on at import (the RC and mechanical scales differ by ~1e3, and the energy
accumulators difference large numbers).
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from .actuators import DCDEA_LS, DCDEA_RR, SCDEA_LS, ConeActuator, ConeState, Loading  # noqa: E402
from .config import ConfigError, Model, load_config, model_from_dict  # noqa: E402
from .materials import GentMaxwell  # noqa: E402
from .membrane import ConeMembrane  # noqa: E402
from .payloads import LinearViscous  # noqa: E402
from .protocol import STATUS, CycleMetrics, StepControl, run_protocol  # noqa: E402
from .signals import SquareWave  # noqa: E402
from .simulate import simulate  # noqa: E402
from .solver import LawsonRK4, SemilinearTerm  # noqa: E402
from .sweep import SweepError, make_loadings, sweep  # noqa: E402
from .powermap import powermap  # noqa: E402

__all__ = [
    "ConeActuator", "ConeMembrane", "ConeState", "ConfigError", "CycleMetrics", "DCDEA_LS",
    "DCDEA_RR", "GentMaxwell", "LawsonRK4", "LinearViscous", "Loading", "Model", "SCDEA_LS",
    "STATUS", "SemilinearTerm", "SquareWave", "StepControl", "SweepError", "load_config",
    "make_loadings", "model_from_dict", "powermap", "run_protocol", "simulate", "sweep",
]
