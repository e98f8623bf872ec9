"""A discrete PID controller with a filtered derivative and back-calculation anti-windup."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, check_scalar_param, error_if_not_finite, error_if_not_positive
from .._dtypes import param_dtype
from .base import AbstractController, check_limits


class PID(AbstractController):
    r"""Discrete PID with a filtered derivative on the measurement and back-calculation anti-windup.

    With $e_k = r_k - y_k$ and the sample period $\Delta$:

    $D_k = \dfrac{T_f D_{k-1} - k_d (y_k - y_{k-1})}{T_f + \Delta}$ (backward Euler of $-k_d\,s/(1 + T_f s)$ on
    $y$: no derivative kick when the reference jumps),

    $v_k = u_0 + k_p e_k + I_k + D_k$, $\quad u_k = \mathrm{clip}(v_k, u_{\min}, u_{\max})$,

    $I_{k+1} = I_k + k_i \Delta\, e_k + \dfrac{\Delta}{T_t}(u_k - v_k)$ (Åström's back-calculation: while the
    output saturates the integrator is pulled back towards the limit with time constant $T_t$).

    **Arguments:**

    - `kp`, `ki` [1/s], `kd` [s]: the gains (any sign; units of command per unit of error), finite.
    - `dt`: the sample period $\Delta$ [s] > 0.
    - `offset`: $u_0$, the command at zero error (e.g. the 100 V bias of paper 002's stage).
    - `u_min`, `u_max`: the command limits (default unbounded).
    - `derivative_filter`: $T_f$ [s] ≥ 0 (default `dt`).
    - `tracking_time`: $T_t$ [s] > 0 (default `dt`: the integrator stops at the limit within a sample).

    The derivative starts at rest at the first measurement it reads (no kick from a plant that does not start at
    0), unless `init(measurement)` gives the previous one.

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
        dtype = param_dtype(kp, ki, kd, dt, offset, u_min, u_max, derivative_filter, tracking_time)
        self.kp, self.ki, self.kd = (check_scalar_param(x, n, dtype) for x, n in ((kp, "kp"), (ki, "ki"), (kd, "kd")))
        self.dt = check_scalar_param(dt, "dt", dtype)
        self.offset = check_scalar_param(offset, "offset", dtype)
        self.u_min = check_scalar_param(u_min, "u_min", dtype, finite=False)
        self.u_max = check_scalar_param(u_max, "u_max", dtype, finite=False)
        self.derivative_filter = check_scalar_param(self.dt if derivative_filter is None else derivative_filter,
                                                    "derivative_filter", dtype)
        self.tracking_time = check_scalar_param(self.dt if tracking_time is None else tracking_time, "tracking_time",
                                                dtype)
        checked = self.check()  # the value rules, one place for construction and for every call
        self.dt, self.derivative_filter = checked.dt, checked.derivative_filter
        self.tracking_time, self.u_min, self.u_max = checked.tracking_time, checked.u_min, checked.u_max

    def check(self) -> "PID":
        m = error_if_not_finite(self, ("kp", "ki", "kd", "offset"))
        m = error_if_not_positive(m, ("dt", "derivative_filter", "tracking_time"), allow_zero=("derivative_filter",))
        return eqx.tree_at(lambda p: (p.u_min, p.u_max), m, check_limits(m.u_min, m.u_max))

    def init(self, measurement: ArrayLike | None = None) -> Float[Array, "4"]:
        """The state `[I, y_prev, D, started]`: integrator empty, derivative at rest at `measurement` (default: at
        the first measurement `step` reads)."""
        zero = jnp.zeros((), self.kp.dtype)
        if measurement is None:
            return jnp.stack([zero, zero, zero, zero])
        return jnp.stack([zero, jnp.asarray(measurement, self.kp.dtype), zero, jnp.ones((), self.kp.dtype)])

    def step(self, state: Float[Array, "4"], reference: Array, measurement: Array) -> tuple[Array, Array]:
        if jnp.shape(state) != (4,):
            raise PiezojaxValueError(f"`state` must be the PID's state of shape (4,) from `init()`, got shape "
                                     f"{jnp.shape(state)}")
        integral, deriv, started = state[0], state[2], state[3]
        y_prev = jnp.where(started > 0, state[1], measurement)
        e = reference - measurement
        deriv = (self.derivative_filter * deriv - self.kd * (measurement - y_prev)) / (self.derivative_filter + self.dt)
        v = self.offset + self.kp * e + integral + deriv
        u = jnp.clip(v, self.u_min, self.u_max)
        integral = integral + self.ki * self.dt * e + self.dt / self.tracking_time * (u - v)
        return jnp.stack([integral, measurement, deriv, jnp.ones_like(started)]), u
