"""Calibration: fit any subset of a model's parameters to measured data.

- :mod:`.data`: measured data (time series, frequency responses), from CSV or NetCDF;
- :mod:`.params`: parameter paths, transforms and bounds;
- :mod:`.predictors`: the model's output at the data (``predict(model, data)``);
- :mod:`.objective`: residuals, loss and their compiled derivatives;
- :mod:`.optimisers`: L-BFGS, Adam, Gauss-Newton/Levenberg-Marquardt, differential evolution;
- :mod:`.fit`: :func:`calibrate`, its result, the error metrics and the curvature;
- :mod:`.fitted_toml`: the fitted-config writer.

The public names are re-exported here; the figure is :func:`jaxdea.plotting.plot_fit`.
"""

from .._checks import CalibrationError, DataError
from ..params import Param, get_params, make_params, parameter_names, resolve_names, set_params
from .data import Data, FrequencyResponse, TimeSeries, data_from_columns, load_data, save_data
from .fit import CalibrationResult, calibrate, error_metrics
from .fitted_toml import config_keys, fitted_config_text, write_fitted_config
from .objective import Objective
from .optimisers import DE, DE_PAPER, LBFGS, LM, METHODS, AbstractOptimiser, Adam, optimiser_for
from .predictors import PREDICTORS, default_predict, frequency_response, transient_predictor

__all__ = [
    "DE", "DE_PAPER", "LBFGS", "LM", "METHODS", "PREDICTORS", "AbstractOptimiser", "Adam",
    "CalibrationError", "CalibrationResult", "Data", "DataError", "FrequencyResponse",
    "Objective", "Param", "TimeSeries", "calibrate", "config_keys", "data_from_columns",
    "default_predict", "error_metrics", "fitted_config_text", "frequency_response",
    "get_params", "load_data", "make_params", "optimiser_for", "parameter_names",
    "resolve_names", "save_data", "set_params", "transient_predictor", "write_fitted_config",
]
