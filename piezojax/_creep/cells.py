r"""The creep blocks as per-sample cells, for `pj.Actuator`'s one-loop forward pass.

`pj.Actuator.simulate` runs hysteresis, creep and dynamics in one loop when every block has a cell (its creep an
`AbstractFusedCreep`, whose `zoh_cell` is one of these). A Kelvin–Voigt
chain or a lag creep, $d\,u + \sum_i c_i\,\mathcal{L}_{\tau_i}[u]$, is `LagCell`: the ZOH lags of `lags.lag_sum`
with the same arithmetic, sample by sample. A `LinearCreep` is its system's `DiscreteStateSpace`. The logarithmic
law has infinite memory and no cell.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .lags import zoh_lag_coefficients


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
