"""Calibration: fit any subset of a model's parameters to measured data.

Measured data (:mod:`.data`), parameter paths and transforms, predictors, the objective,
the optimisers (L-BFGS, Adam, Gauss-Newton/Levenberg-Marquardt, differential evolution) and
the fitted-config writer. The public names are re-exported here.
"""

from .._checks import CalibrationError, DataError
from .data import Data, FrequencyResponse, TimeSeries, data_from_columns, load_data, save_data
from .fit import (DE_PAPER, METHODS, CalibrationResult, calibrate, error_metrics,
                  fitted_config_text, frequency_response, get_params, make_params,
                  parameter_names, plot_fit, resolve_names, set_params, transient_predictor,
                  write_fitted_config)

__all__ = [
    "DE_PAPER", "METHODS", "CalibrationError", "CalibrationResult", "Data", "DataError",
    "FrequencyResponse", "TimeSeries", "calibrate", "data_from_columns", "error_metrics",
    "fitted_config_text", "frequency_response", "get_params", "load_data", "make_params",
    "parameter_names", "plot_fit", "resolve_names", "save_data", "set_params",
    "transient_predictor", "write_fitted_config",
]
