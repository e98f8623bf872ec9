r"""A pure dead time of fractional samples: the latency of an amplifier or a sensor."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_positive, check_positive_param, check_signal, check_step
from .._custom_types import Signal, SignalLike
from .._dtypes import module_float_dtype


class Delay(eqx.Module):
    r"""A dead time $\tau \ge 0$ [s]: $y(t) = u(t - \tau)$, for any $\tau$, a whole number of samples or not.

    A sampled input is read between its samples by the cubic Catmull–Rom interpolant (exact for a quadratic; the
    samples themselves at a whole number of samples), so the output is continuously differentiable in $\tau$: a
    delay can be fitted by least squares with the other parameters. With $d = \tau/\Delta t = k + f$ ($k$ whole,
    $0 \le f < 1$), sample $n$ of the output is the interpolant at $n - d$, between the input's samples
    $n - k - 1$ and $n - k$ (with $u_{n-k-2}$ and $u_{n-k+1}$ as its neighbours). Before the record the input is
    held at its first sample (a record that starts at rest, at 0, stays there), after it at its last (needed only by
    the interpolant's last neighbour).

    `jit`, `vmap`, `grad` and `jacfwd` with respect to $\tau$ and the input alike.

    **Arguments:**

    - `time`: $\tau \ge 0$ [s], finite.

    ```python
    delay = pj.Delay(2.5e-4)
    y = delay(u, dt=1e-4)          # u read 2.5 samples late
    ```
    """

    time: Float[Array, ""]

    def __init__(self, time: ArrayLike):
        self.time = check_positive_param(time, "time", allow_zero=True)

    def samples(self, dt: ArrayLike) -> Float[Array, ""]:
        r"""The delay in samples of step `dt`, $\tau/\Delta t$."""
        return self.time / dt

    def simulate(self, u: SignalLike, dt: ArrayLike) -> Signal:
        """The input `u` (shape `(time,)`, sampled every `dt` seconds) delayed by `time`."""
        dtype = module_float_dtype(self, u, dt)
        u = check_signal(u, "u", dtype)
        dt = check_step(dt, "dt", dtype)
        tau = check_positive(self.time.astype(dtype), "time", allow_zero=True)
        return delay_signal(u, tau / dt)

    def __call__(self, u: SignalLike, dt: ArrayLike) -> Signal:
        """Same as `simulate`."""
        return self.simulate(u, dt)


def delay_signal(u: Float[Array, " time"], d: Float[Array, ""]) -> Float[Array, " time"]:
    r"""`u` read `d` samples late ($d \ge 0$, not necessarily whole) by the Catmull–Rom interpolant, held at its
    first sample before the record and at its last after it (see `Delay`)."""
    n = u.shape[0]
    k = jnp.floor(d)
    t = 1.0 - (d - k)  # position within the interval [n - k - 1, n - k]
    i = jnp.arange(n, dtype=jnp.int32) - k.astype(jnp.int32) - 1

    def at(j):
        return u[jnp.clip(j, 0, n - 1)]

    t2, t3 = t * t, t * t * t
    # the Catmull-Rom weights: (0, 1, 0, 0) at t = 0 and (0, 0, 1, 0) at t = 1, exactly
    w0, w1 = 0.5 * (2.0 * t2 - t - t3), 0.5 * (2.0 - 5.0 * t2 + 3.0 * t3)
    w2, w3 = 0.5 * (t + 4.0 * t2 - 3.0 * t3), 0.5 * (t3 - t2)
    return w0 * at(i - 1) + w1 * at(i) + w2 * at(i + 1) + w3 * at(i + 2)
