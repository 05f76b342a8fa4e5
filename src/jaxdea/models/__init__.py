"""Models only: one module per configuration (no loaders, no studies).

The square-wave cones of paper 000 share :mod:`.cone` (state, loading, vector field, RC
linearisation); :mod:`.mass_cone`, :mod:`.planar` and :mod:`.rotary` are the viscoelastic
and rotary families of papers 001-004.
"""

from .cone import ConeActuator, ConeState, Loading, Model
from .double_cone import DCDEA_LS, DCDEA_RR
from .single_cone import SCDEA_LS

__all__ = ["ConeActuator", "ConeState", "Loading", "Model", "SCDEA_LS", "DCDEA_RR", "DCDEA_LS"]
