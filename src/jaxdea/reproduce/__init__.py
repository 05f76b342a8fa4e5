"""Reproductions of the source papers' studies: paper 000's claims as a calibration loss,
its calibration, and its figures and claims table regenerated in one command.

- :mod:`.peaks`: P_max of many designs at once over every drive case (lane engine);
- :mod:`.claims`: the published numbers and findings as claims, and the hinge loss;
- :mod:`.objective`: that loss as an objective of the fitted constants (DE, L-BFGS);
- :mod:`.paper000`: what is fitted, the bounds, the staged calibration, the configs;
- :mod:`.figures`: Figs 6, 7, 9, 10, 11 and the trade-off plot;
- :mod:`.study`: :func:`reproduce_paper000` (``jaxdea reproduce paper000``).
"""

from .claims import CLAIMS, Above, Claim, Near, loss, met, quantities_of
from .objective import ClaimsObjective
from .paper000 import BOUNDS, FIT, FitPlan, calibrate_paper000, load_models, write_configs
from .peaks import CASES, Case, PeakSearch, peak_table
from .study import SIZES, reproduce_paper000

__all__ = ["BOUNDS", "CASES", "CLAIMS", "FIT", "SIZES", "Above", "Case", "Claim",
           "ClaimsObjective", "FitPlan", "Near", "PeakSearch", "calibrate_paper000",
           "load_models", "loss", "met", "peak_table", "quantities_of", "reproduce_paper000",
           "write_configs"]
