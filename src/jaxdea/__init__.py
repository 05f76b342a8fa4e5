"""jaxdea: batched, differentiable JAX simulator of cone dielectric elastomer actuators.

The public API, grouped by wing (lowest first; a wing imports only from its own or lower
wings, see ``docs/architecture.md``). Everything not exported here may change.

- leaves: constitutive laws, the cone membrane, drive signals, payloads, the exponential RK4 solvers
- models: the cone configurations of paper 000 and the viscoelastic and rotary families
- config: :func:`load_config` -> a validated model (TOML, SI units)
- engine: the lane engine (:func:`run_protocol`), step control, cycle metrics, status codes,
  :func:`use_cpu_cores`, :func:`use_compile_cache`
- studies: :func:`sweep`, :func:`powermap` (and :func:`open_map` to read one back),
  :func:`simulate`, :func:`transient`, :func:`rotary_study`
- calibration: :func:`calibrate` and measured data (:func:`load_data`)

Importing jaxdea switches on ``jax_enable_x64`` and changes no other global JAX state (a test
checks this). float64 is needed, not a taste: the RC charging (tens of microseconds) and the
mechanics (milliseconds) differ by ~1e3 in time scale, and the energy accumulators that give
P_out and P_in difference large numbers over hundreds of cycles; every model and config is
built in float64. A program that wants float32 elsewhere can still pass float32 arrays to
its own code.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

# errors (every user error is one of these, all ValueError subclasses)
from ._checks import (CalibrationError, ConfigError, DataError, FieldWarning,  # noqa: E402
                      JaxdeaError, SweepError)

# leaves
from .materials import GentKelvinChain, GentMaxwell, GentSpringDashpot  # noqa: E402
from .membrane import ConeMembrane  # noqa: E402
from . import payloads  # noqa: E402
from .payloads import Combined, Drag, Elastic, Gravity, LinearViscous, PayloadLaw  # noqa: E402
from .signals import MultiSine, Sine, SquareWave, TriangularPattern, voltage_pattern  # noqa: E402
from .solver import ExponentialRK4, LawsonRK4, SemilinearTerm  # noqa: E402

# models
from .models import DCDEA_LS, DCDEA_RR, SCDEA_LS, ConeActuator, ConeState, Loading, Model  # noqa
from .models.mass_cone import MassCone, huang2020, nouhi_kelvin, prestretch_report  # noqa: E402
from .models.planar import PlanarDEA, gu2017  # noqa: E402
from .models.rotary import RotaryDCDEA  # noqa: E402

# config
from .config import load_config, load_payload, model_from_dict  # noqa: E402

# engine
from .engine.batch import EARLY_EXIT  # noqa: E402
from .engine.lanes import run_protocol  # noqa: E402
from .engine.metrics import STATUS, CycleMetrics  # noqa: E402
from .engine.protocols import Continuation, Paper, Periodic  # noqa: E402
from .engine.sharding import use_compile_cache, use_cpu_cores  # noqa: E402
from .engine.step_control import StepControl  # noqa: E402

# studies
from .studies.design import design_map, peak_power, steady_objectives  # noqa: E402
from .studies.loadings import make_loadings  # noqa: E402
from .studies.mapstore import open_map  # noqa: E402
from .studies.optimise import OptimiseResult, optimise  # noqa: E402
from .studies.powermap import powermap  # noqa: E402
from .studies.rotary import rotary_study  # noqa: E402
from .studies.simulate import simulate  # noqa: E402
from .studies.sweep import sweep  # noqa: E402
from .studies.transient import (amplitude_frequency, displacement, hysteresis_area,  # noqa
                                transient)

# calibration
from .calibration import (CalibrationResult, FrequencyResponse, TimeSeries,  # noqa: E402
                          calibrate, load_data, parameter_names)

__version__ = "0.1.0"

__all__ = [
    # errors
    "CalibrationError", "ConfigError", "DataError", "FieldWarning", "JaxdeaError", "SweepError",
    # leaves
    "Combined", "ConeMembrane", "Drag", "Elastic", "ExponentialRK4", "GentKelvinChain",
    "GentMaxwell", "GentSpringDashpot", "Gravity", "LawsonRK4", "LinearViscous", "MultiSine",
    "PayloadLaw",
    "SemilinearTerm", "Sine", "SquareWave", "TriangularPattern",
    "payloads", "voltage_pattern",
    # models
    "ConeActuator", "ConeState", "DCDEA_LS", "DCDEA_RR", "Loading", "MassCone", "Model",
    "PlanarDEA", "RotaryDCDEA", "SCDEA_LS", "gu2017", "huang2020", "nouhi_kelvin",
    "prestretch_report",
    # config
    "load_config", "load_payload", "model_from_dict",
    # engine
    "EARLY_EXIT", "STATUS", "Continuation", "CycleMetrics", "Paper", "Periodic", "StepControl",
    "run_protocol", "use_compile_cache", "use_cpu_cores",
    # studies
    "OptimiseResult", "amplitude_frequency", "design_map", "displacement", "hysteresis_area",
    "make_loadings", "open_map", "optimise", "peak_power", "powermap", "rotary_study", "simulate",
    "steady_objectives", "sweep", "transient",
    # calibration
    "CalibrationResult", "FrequencyResponse", "TimeSeries", "calibrate", "load_data",
    "parameter_names",
]
