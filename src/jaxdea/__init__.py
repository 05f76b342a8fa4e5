"""jaxdea: batched, differentiable JAX simulator of cone dielectric elastomer actuators.

Public API (everything else may change):

- :func:`load_config` -> :class:`Model` (validated TOML config, SI units)
- :func:`sweep` -> ``xarray.Dataset`` over frequency (paper 000 protocol)
- :func:`powermap` -> ``xarray.Dataset`` over payload mass x damping x frequency (x phase):
  chunked, sharded over all JAX devices, resumable from a Zarr/NetCDF store
- :func:`simulate` -> trajectory of one drive case (diffrax)
- :class:`RotaryDCDEA` (paper 003 rotational double cone) and :func:`rotary_study` ->
  ``xarray.Dataset`` of the steady angle over inner radius x half spacer length
- building blocks: :class:`GentMaxwell`, :class:`ConeMembrane`, :class:`SCDEA_LS`,
  :class:`DCDEA_RR`, :class:`DCDEA_LS`, :class:`SquareWave`, :class:`LinearViscous`,
  :class:`LawsonRK4`, :func:`run_protocol`, :class:`StepControl`.
- :func:`use_cpu_cores`: one JAX CPU device per core (call first; sweeps and maps then run
  on every core). :data:`EARLY_EXIT`: the paper protocol's early-exit tolerance.

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
from .sweep import EARLY_EXIT, SweepError, make_loadings, sweep  # noqa: E402
from .sharding import use_cpu_cores  # noqa: E402
from .powermap import powermap  # noqa: E402
from .actuators.rotary import RotaryDCDEA, rotary_study  # noqa: E402
from .caldata import DataError, FrequencyResponse, TimeSeries, load_data  # noqa: E402
from .calibrate import CalibrationError, CalibrationResult, calibrate, parameter_names  # noqa: E402,E501
from .materials import GentKelvinChain, GentSpringDashpot  # noqa: E402
from .signals import MultiSine, Sine, TriangularPattern, voltage_pattern  # noqa: E402
from .actuators.planar import PlanarDEA, gu2017  # noqa: E402
from .actuators.mass_cone import MassCone, huang2020, nouhi_kelvin, prestretch_report  # noqa: E402,E501
from .viscoelastic import amplitude_frequency, displacement, hysteresis_area, transient  # noqa: E402,E501

__all__ = [
    "RotaryDCDEA", "rotary_study",
    "GentKelvinChain", "GentSpringDashpot", "MassCone", "MultiSine", "PlanarDEA", "Sine",
    "TriangularPattern", "amplitude_frequency", "displacement", "gu2017", "huang2020",
    "hysteresis_area", "nouhi_kelvin", "prestretch_report", "transient", "voltage_pattern",
    "CalibrationError", "CalibrationResult", "DataError", "FrequencyResponse", "TimeSeries",
    "calibrate", "load_data", "parameter_names",
    "ConeActuator", "ConeMembrane", "ConeState", "ConfigError", "CycleMetrics", "DCDEA_LS",
    "DCDEA_RR", "GentMaxwell", "LawsonRK4", "LinearViscous", "Loading", "Model", "SCDEA_LS",
    "STATUS", "SemilinearTerm", "SquareWave", "StepControl", "SweepError", "load_config",
    "make_loadings", "model_from_dict", "powermap", "run_protocol", "simulate", "sweep",
    "EARLY_EXIT", "use_cpu_cores",
]
