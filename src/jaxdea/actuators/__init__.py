"""Cone actuator configurations; each is one module on top of :mod:`.base`."""

from .base import ConeActuator, ConeState, Loading
from .double_cone import DCDEA_LS, DCDEA_RR
from .single_cone import SCDEA_LS

__all__ = ["ConeActuator", "ConeState", "Loading", "SCDEA_LS", "DCDEA_RR", "DCDEA_LS"]
