r"""The creep blocks as per-sample cells, for `pj.Actuator`'s one-loop forward pass.

`pj.Actuator.simulate` runs hysteresis, creep and dynamics in one loop when every block has a cell. A Kelvin–Voigt
chain or a lag creep, $d\,u + \sum_i c_i\,\mathcal{L}_{\tau_i}[u]$, is `LagCell`: the ZOH lags of `lags.lag_sum`
with the same arithmetic, sample by sample. A `LinearCreep` is its system's `DiscreteStateSpace`. The logarithmic
law has infinite memory and no cell.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .._linear.discretise import DiscreteStateSpace
from .base import AbstractCreep
from .kelvin_voigt import KelvinVoigtCreep
from .lag import LagCreep
from .lags import zoh_lag_coefficients
from .linear import LinearCreep

# the creep types `zoh_cell` samples
ZOH_CELL_TYPES = (KelvinVoigtCreep, LagCreep, LinearCreep)


class LagCell(eqx.Module):
    r"""$y_k = d\,u_k + c \cdot x_k$, $x_{k+1} = a \odot x_k + (1 - a) \odot u_k$ from $x_0 = 0$, with
    $a_i = e^{-dt/\tau_i}$: unit-gain ZOH lags weighted by $c$, plus a feed-through $d$."""

    a: Array
    one_minus_a: Array
    c: Array
    d: Array

    def __init__(self, c: Array, tau: Array, d: Array, dt: Array):
        self.a, self.one_minus_a = zoh_lag_coefficients(tau, dt)
        self.c, self.d = c, d

    @property
    def order(self) -> int:
        return self.c.shape[0]

    def step(self, x: Array, uk: Array) -> tuple[Array, Array]:
        """One sample: `(x_next, y_k)` (the arithmetic of `lags.lag_scan`)."""
        return self.a * x + self.one_minus_a * uk, self.d * uk + jnp.sum(self.c * x)


def zoh_cell(creep: AbstractCreep, dt: Array) -> LagCell | DiscreteStateSpace:
    """The (checked) creep block `creep` of one of `ZOH_CELL_TYPES` sampled with a zero-order hold at step `dt`."""
    if isinstance(creep, KelvinVoigtCreep):
        return LagCell(1 / creep.stiffnesses, creep.time_constants, creep.instantaneous_gain(), dt)
    if isinstance(creep, LagCreep):
        return LagCell(creep.fractions, creep.time_constants, creep.feedthrough(), dt)
    if isinstance(creep, LinearCreep):
        return creep.system.discretise(dt, "zoh")
    raise TypeError(f"no cell for {type(creep).__name__}")
