"""Refinement after a fit: hysteresis plays re-seeded, swapped or placed anew (`plays.py`), creep lags moved
(`lags.py`), and the rounds that refit from them while the cost falls (`rounds.py`)."""

from .lags import relocated_lags as relocated_lags
from .plays import reseeded as reseeded
from .rounds import (
    RESEED_GAIN as RESEED_GAIN,
    RESEED_ROUNDS as RESEED_ROUNDS,
    refine as refine,
    silent as silent,
    whole_run as whole_run,
)
