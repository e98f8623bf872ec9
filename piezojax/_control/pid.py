"""A discrete PID controller with a filtered derivative and back-calculation anti-windup."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, as_parameter_array, check_positive, check_value
from .base import AbstractController


def _scalar(x: ArrayLike, name: str) -> Array:
    a = as_parameter_array(x, name)
    if a.ndim != 0:
        raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {a.shape}")
    return a


class PID(AbstractController):
    r"""Discrete PID with a filtered derivative on the measurement and back-calculation anti-windup.

    With $e_k = r_k - y_k$ and the sample period $\Delta$:

    $D_k = \dfrac{T_f D_{k-1} - k_d (y_k - y_{k-1})}{T_f + \Delta}$ (backward Euler of $-k_d\,s/(1 + T_f s)$ on
    $y$: no derivative kick when the reference jumps),

    $v_k = u_0 + k_p e_k + I_k + D_k$, $\quad u_k = \mathrm{clip}(v_k, u_{\min}, u_{\max})$,

    $I_{k+1} = I_k + k_i \Delta\, e_k + \dfrac{\Delta}{T_t}(u_k - v_k)$ (Åström's back-calculation: while the
    output saturates the integrator is pulled back towards the limit with time constant $T_t$).

    **Arguments:**

    - `kp`, `ki` [1/s], `kd` [s]: the gains (any sign; units of command per unit of error).
    - `dt`: the sample period $\Delta$ [s] > 0.
    - `offset`: $u_0$, the command at zero error (e.g. the 100 V bias of paper 002's stage).
    - `u_min`, `u_max`: the command limits (default unbounded).
    - `derivative_filter`: $T_f$ [s] ≥ 0 (default `dt`).
    - `tracking_time`: $T_t$ [s] > 0 (default `dt`: the integrator stops at the limit within a sample).

    ```python
    pid = pj.PID(kp=2e5, ki=4e7, kd=0.0, dt=1e-3, offset=100.0, u_min=-20.0, u_max=200.0)
    rec = pj.closed_loop(pid, plant, reference)
    ```
    """

    kp: Float[Array, ""]
    ki: Float[Array, ""]
    kd: Float[Array, ""]
    dt: Float[Array, ""]
    offset: Float[Array, ""]
    u_min: Float[Array, ""]
    u_max: Float[Array, ""]
    derivative_filter: Float[Array, ""]
    tracking_time: Float[Array, ""]

    def __init__(
        self,
        kp: ArrayLike,
        ki: ArrayLike = 0.0,
        kd: ArrayLike = 0.0,
        *,
        dt: ArrayLike,
        offset: ArrayLike = 0.0,
        u_min: ArrayLike = -jnp.inf,
        u_max: ArrayLike = jnp.inf,
        derivative_filter: ArrayLike | None = None,
        tracking_time: ArrayLike | None = None,
    ):
        self.kp, self.ki, self.kd = _scalar(kp, "kp"), _scalar(ki, "ki"), _scalar(kd, "kd")
        self.dt = check_positive(_scalar(dt, "dt"), "dt")
        self.offset = _scalar(offset, "offset")
        self.u_min, self.u_max = _scalar(u_min, "u_min"), _scalar(u_max, "u_max")
        self.u_max = check_value(self.u_max, lambda a: a > self.u_min, "`u_max` must be greater than `u_min`")
        self.derivative_filter = check_positive(
            _scalar(self.dt if derivative_filter is None else derivative_filter, "derivative_filter"),
            "derivative_filter", allow_zero=True,
        )
        self.tracking_time = check_positive(
            _scalar(self.dt if tracking_time is None else tracking_time, "tracking_time"), "tracking_time"
        )

    def init(self, measurement: ArrayLike = 0.0) -> Float[Array, "3"]:
        """The state `[I, y_prev, D]`: integrator empty, derivative at rest at `measurement`."""
        zero = jnp.zeros((), self.kp.dtype)
        return jnp.stack([zero, jnp.asarray(measurement, self.kp.dtype), zero])

    def step(self, state: Float[Array, "3"], reference: Array, measurement: Array) -> tuple[Array, Array]:
        integral, y_prev, deriv = state[0], state[1], state[2]
        e = reference - measurement
        deriv = (self.derivative_filter * deriv - self.kd * (measurement - y_prev)) / (self.derivative_filter + self.dt)
        v = self.offset + self.kp * e + integral + deriv
        u = jnp.clip(v, self.u_min, self.u_max)
        integral = integral + self.ki * self.dt * e + self.dt / self.tracking_time * (u - v)
        return jnp.stack([integral, measurement, deriv]), u
