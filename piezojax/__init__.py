"""piezojax: differentiable models of piezoelectric actuators and their self-sensing electronics."""

from ._checks import PiezojaxValueError as PiezojaxValueError
from ._hysteresis.base import AbstractHysteresis as AbstractHysteresis

__version__ = "0.1.0"
