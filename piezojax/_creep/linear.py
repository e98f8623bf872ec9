"""LTI creep: a (low-order) transfer function $F_C(s)$ from the voltage to the creep displacement."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError
from .._dtypes import matmul
from .._linear.base import AbstractLinearSystem
from .._linear.discretise import discretise_state_space
from .._linear.stable import StableTransferFunction
from .base import AbstractFusedCreep


class LinearCreep(AbstractFusedCreep):
    r"""Creep as a linear time-invariant transfer function (paper 001, eq. 9):

    $$F_C(s) = \frac{a_0 s^4 + a_1 s^3 + a_2 s^2 + a_3 s + a_4}{s^4 + b_1 s^3 + b_2 s^2 + b_3 s + b_4}.$$

    Any `AbstractLinearSystem` can be wrapped (order up to 4 in the paper; higher orders work too). For fitting use
    a `StableTransferFunction` (poles as $\omega_n, \zeta > 0$ and real poles $< 0$), so every parameter value is a
    stable creep; `LinearCreep.from_tf(num, den)` builds one from polynomial coefficients. The simulation is the
    linear block's exact ZOH/FOH discretisation.

    Step response $h(t) = D + C\left(\int_0^t e^{A\sigma} d\sigma\right) B$ (matrix exponential, exact).

    $h(0^+) = D = a_0$: with $a_0 = 1$ and $F_C(0) = 1 + $ creep, the block is DC-normalised at $0^+$ for use in series
    after the hysteresis; with $a_0 = 0$ it is the creep part alone, for use in parallel (as in paper 001).

    **Arguments:**

    - `system`: the transfer function, an `AbstractLinearSystem`.

    **Example:**

    ```python
    creep = pj.LinearCreep.from_tf([0.0, 0.0, 0.0, 0.02, 0.002], [1.0, 1.2, 0.4, 0.04, 0.001])
    y = creep.simulate(v, dt=1e-2)
    ```
    """

    system: AbstractLinearSystem

    def __init__(self, system: AbstractLinearSystem):
        if not isinstance(system, AbstractLinearSystem):
            raise PiezojaxValueError(
                f"`system` must be an AbstractLinearSystem (e.g. StableTransferFunction), got {type(system).__name__}"
            )
        self.system = system

    @classmethod
    def from_tf(cls, num: ArrayLike, den: ArrayLike, dc_normalised: bool = False) -> "LinearCreep":
        """A stable-by-construction creep transfer function from coefficients (highest power first).

        Raises a `ValueError` naming `den` if the denominator is not stable (a creep must settle).
        See `StableTransferFunction.from_tf`.
        """
        return cls(StableTransferFunction.from_tf(num, den, dc_normalised=dc_normalised))

    def check(self) -> "LinearCreep":
        """`self`: the system checks its coefficients whenever it builds its realisation (`state_space()`)."""
        return self

    def settled_gain(self) -> Array:
        """$F_C(0)$, the static gain of the transfer function."""
        return self.system.dc_gain()

    def step_response(self, t: ArrayLike) -> Array:
        A, B, C, D = self.system.state_space()
        t = jnp.asarray(t, A.dtype)
        if A.shape[0] == 0:
            return jnp.broadcast_to(D, t.shape)

        def one(ti):
            positive = ti > 0
            safe = jnp.where(positive, ti, jnp.ones_like(ti))
            d = discretise_state_space(A, B, C, D, safe, "zoh")  # Bd = (∫_0^t e^{Aσ} dσ) B
            return jnp.where(positive, D + matmul(C, d.Bd), D)

        flat = jax.vmap(one)(jnp.ravel(t))
        return flat.reshape(t.shape)

    def zoh_cell(self, dt: Array):
        return self.system.discretise(dt, "zoh")

    def instantaneous_gain(self) -> Array:
        return self.system.state_space()[3]

    def _simulate(self, u: Array, dt: Array, hold: str) -> Array:
        return self.system.simulate(u, dt, hold=hold)
