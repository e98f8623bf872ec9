"""Creep as a fraction of the response arriving with lags: a DC-normalised Kelvin–Voigt chain."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import check_positive, check_value
from .base import AbstractFusedCreep
from .cells import LagCell
from .kelvin_voigt import paired_vectors
from .lags import lag_sum


def _check_fractions(alpha: Array) -> Array:
    return check_value(
        alpha,
        lambda a: jnp.all(jnp.isfinite(a) & (a > 0)) & (jnp.sum(a) <= 1),
        "`fractions` must be finite and > 0 with a sum <= 1",
    )


class LagCreep(AbstractFusedCreep):
    r"""Creep with instantaneous feed-through: a fraction $\alpha_i$ of the response arrives with lag $\tau_i$.

    $$\mathcal{C}(s) = \Big(1 - \sum_i \alpha_i\Big) + \sum_i \frac{\alpha_i}{1 + \tau_i s},\qquad
    h(t) = 1 - \sum_i \alpha_i\, e^{-t/\tau_i}.$$

    DC-normalised ($h(\infty) = 1$) with $h(0^+) = 1 - \sum\alpha_i$: the block for `Actuator(structure="series")`,
    after the hysteresis, where a free static gain would duplicate the hysteresis weights. A real actuator answers a
    voltage step mostly at once and the rest over milliseconds to seconds; a plain first-order lag ($\sum\alpha = 1$)
    cannot follow the step and a steady loop's phase lag at once. It is a `KelvinVoigtCreep` with
    $1/k_0 = 1 - \sum\alpha_i$ and $1/k_i = \alpha_i$, simulated by the same lags (`lags.lag_sum`).

    **Arguments:**

    - `fractions`: $\alpha_i > 0$ with $\sum_i \alpha_i \le 1$, shape `(n,)`; fit them with `pj.Fractions`, which
      keeps every value valid.
    - `time_constants`: $\tau_i > 0$ [s], shape `(n,)`.

    **Example:**

    ```python
    creep = pj.LagCreep(fractions=[0.1], time_constants=[5e-3])   # 90 % at once, 10 % with a 5 ms lag
    y = creep.simulate(jnp.ones(100), dt=1e-3)                     # y = 1 - 0.1 exp(-t / 5 ms)
    ```
    """

    fractions: Array = eqx.field(converter=jnp.asarray)
    time_constants: Array = eqx.field(converter=jnp.asarray)

    def __init__(self, fractions: ArrayLike, time_constants: ArrayLike):
        alpha, tau = paired_vectors(fractions, "fractions", time_constants, "time_constants")
        self.fractions = _check_fractions(alpha)
        self.time_constants = check_positive(tau, "time_constants")

    def check(self) -> "LagCreep":
        checked = (_check_fractions(self.fractions), check_positive(self.time_constants, "time_constants"))
        return eqx.tree_at(lambda m: (m.fractions, m.time_constants), self, checked)

    def zoh_cell(self, dt: Array) -> LagCell:
        return LagCell(self.fractions, self.time_constants, self.feedthrough(), dt)

    def feedthrough(self) -> Array:
        r"""$1 - \sum_i \alpha_i$, the part of the response that follows the input at once."""
        return 1 - jnp.sum(self.fractions)

    def step_response(self, t: ArrayLike) -> Array:
        t = jnp.asarray(t)
        return self.feedthrough() + jnp.sum(-jnp.expm1(-t[..., None] / self.time_constants) * self.fractions, axis=-1)

    def instantaneous_gain(self) -> Array:
        return self.feedthrough()

    def settled_gain(self) -> Array:
        return jnp.ones((), self.fractions.dtype)

    def _simulate(self, u: Array, dt: Array, hold: str) -> Array:
        return self.feedthrough() * u + lag_sum(self.fractions, self.time_constants, u, dt, hold)
