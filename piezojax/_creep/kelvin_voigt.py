"""Kelvin–Voigt creep chain: a static compliance plus a sum of first-order lags."""


import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, as_float_array, check_positive, check_same_shape, check_scalar, check_vector
from .._dtypes import common_float_dtype
from .base import AbstractFusedCreep
from .cells import LagCell
from .lags import lag_sum


def paired_vectors(a: ArrayLike, name_a: str, b: ArrayLike, name_b: str) -> tuple[Array, Array]:
    """Two 1-D real vectors of the same shape (values checked by the caller), or one error naming both."""
    x, y = check_vector(a, name_a, finite=False), check_vector(b, name_b, finite=False)
    if x.shape != y.shape:
        raise PiezojaxValueError(
            f"`{name_a}` and `{name_b}` must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    return x, y


class KelvinVoigtCreep(AbstractFusedCreep):
    r"""Kelvin–Voigt creep chain: $y = \left(\frac{1}{k_0} + \sum_i \frac{1}{k_i}\,\frac{1}{1 + \tau_i s}\right) u$.

    A spring $k_0$ in series with Kelvin–Voigt elements (spring $k_i$ parallel to a damper $k_i\tau_i$), driven by
    the input as a force. Step response $h(t) = 1/k_0 + \sum_i (1 - e^{-t/\tau_i})/k_i$.

    Simulation is exact for the held input (diagonal state, one lag per element, $a_i = e^{-dt/\tau_i}$):

    - ZOH: $x_{i,k+1} = a_i x_{i,k} + (1 - a_i)\,u_k$;
    - FOH: $x_{i,k+1} = a_i x_{i,k} + (1 - a_i - b_i)\,u_k + b_i\,u_{k+1}$ with
      $b_i = 1 - \tau_i(1 - a_i)/dt$ (evaluated without cancellation);

    and $y_k = u_k/k_0 + \sum_i x_{i,k}/k_i$, from rest ($x_0 = 0$).

    **Arguments:**

    - `stiffnesses`: $k_i > 0$ (finite), shape `(n,)`.
    - `time_constants`: $\tau_i > 0$ [s] (finite), shape `(n,)`.
    - `k0`: the instantaneous stiffness $k_0 > 0$, or `None` for no instantaneous term ($h(0^+) = 0$: the creep
      part alone, for use in parallel with the hysteresis). Default 1.0 ($h(0^+) = 1$, DC-normalised at $0^+$).

    **Example:**

    ```python
    creep = pj.KelvinVoigtCreep(stiffnesses=[20.0, 50.0], time_constants=[0.5, 20.0])
    y = creep.simulate(jnp.ones(1000), dt=1e-2)  # y[k] = 1 + (1 - exp(-t/0.5))/20 + (1 - exp(-t/20))/50
    ```
    """

    stiffnesses: Array = eqx.field(converter=jnp.asarray)
    time_constants: Array = eqx.field(converter=jnp.asarray)
    k0: Array | None

    def __init__(self, stiffnesses: ArrayLike, time_constants: ArrayLike, k0: ArrayLike | None = 1.0):
        k, tau = paired_vectors(stiffnesses, "stiffnesses", time_constants, "time_constants")
        self.stiffnesses = check_positive(k, "stiffnesses")
        self.time_constants = check_positive(tau, "time_constants")
        if isinstance(k0, int | float) and not isinstance(k0, bool):
            # a plain number follows the parameters' dtype (float32 stays float32)
            k0 = as_float_array(k0, "k0", common_float_dtype(self.stiffnesses, self.time_constants))
        self.k0 = None if k0 is None else check_positive(check_scalar(k0, "k0", finite=False), "k0")

    def check(self) -> "KelvinVoigtCreep":
        check_same_shape(self.stiffnesses, "stiffnesses", self.time_constants, "time_constants")
        k = check_positive(self.stiffnesses, "stiffnesses")
        tau = check_positive(self.time_constants, "time_constants")
        out = eqx.tree_at(lambda m: (m.stiffnesses, m.time_constants), self, (k, tau))
        if self.k0 is not None:
            out = eqx.tree_at(lambda m: m.k0, out, check_positive(self.k0, "k0"))
        return out

    def _c0(self, dtype) -> Array:
        return jnp.zeros((), dtype) if self.k0 is None else 1 / self.k0

    def step_response(self, t: ArrayLike) -> Array:
        t = jnp.asarray(t)
        lags = -jnp.expm1(-t[..., None] / self.time_constants) / self.stiffnesses
        return self._c0(lags.dtype) + jnp.sum(lags, axis=-1)

    def zoh_cell(self, dt: Array) -> LagCell:
        return LagCell(1 / self.stiffnesses, self.time_constants, self.instantaneous_gain(), dt)

    def instantaneous_gain(self) -> Array:
        return self._c0(self.stiffnesses.dtype)

    def settled_gain(self) -> Array:
        r"""$h(\infty) = 1/k_0 + \sum_i 1/k_i$, the limit of `step_response` (written out: evaluating the step
        response at $t = \infty$ gives the value but a NaN derivative in $\tau_i$, $\infty \cdot e^{-\infty}$)."""
        return self._c0(self.stiffnesses.dtype) + jnp.sum(1 / self.stiffnesses)

    def _simulate(self, u: Array, dt: Array, hold: str) -> Array:
        # The one first-order lag of the library (`lags.lag_sum`): elementwise scan body, hand-derived forward
        # sensitivities (under `jax.jacfwd` the parameter directions are one matrix product).
        return self._c0(u.dtype) * u + lag_sum(1 / self.stiffnesses, self.time_constants, u, dt, hold)
