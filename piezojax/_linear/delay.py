r"""A pure dead time of fractional samples: the latency of an amplifier or a sensor."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_positive, check_positive_param, check_signal, check_step
from .._custom_types import Signal, SignalLike
from .._dtypes import module_float_dtype


class Delay(eqx.Module):
    r"""A dead time $\tau \ge 0$ [s]: $y(t) = u(t - \tau)$, for any $\tau$, a whole number of samples or not.

    A sampled input is read between its samples by its monotone cubic interpolant (PCHIP: Fritsch–Carlson slopes,
    the harmonic mean of the neighbouring differences, 0 at a turning point; as `scipy.interpolate.PchipInterpolator`
    on a uniform grid), so the output is continuously differentiable in $\tau$ — a delay is fitted by least squares
    with the other parameters — and never leaves the range of the neighbouring samples: a step is not read with an
    overshoot that a hysteresis operator would remember. With $d = \tau/\Delta t = k + f$ ($k$ whole,
    $0 \le f < 1$), sample $n$ of the output is the interpolant at $n - d$, between the input's samples
    $n - k - 1$ and $n - k$; at a whole number of samples it is the sample itself. Before the record the input is
    held at its first sample (a record that starts at rest, at 0, stays there until the delay has passed), after it
    at its last.

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
    r"""`u` read `d` samples late ($d \ge 0$, not necessarily whole) by its monotone cubic interpolant, held at its
    first sample before the record and at its last after it (see `Delay`)."""
    n = u.shape[0]
    k = jnp.floor(d)
    t = 1.0 - (d - k)  # position within the interval [n - k - 1, n - k]
    i = jnp.arange(n, dtype=jnp.int32) - k.astype(jnp.int32) - 1
    # Fritsch-Carlson slopes at every sample (a held end: a zero difference beyond it, so a zero slope there)
    diff = jnp.diff(u)
    zero = jnp.zeros((1,), u.dtype)
    left, right = jnp.concatenate([zero, diff]), jnp.concatenate([diff, zero])
    same = left * right > 0
    slope = jnp.where(same, 2.0 * left * right / jnp.where(same, left + right, 1.0), 0.0)

    def at(x, j):
        return x[jnp.clip(j, 0, n - 1)]

    p1, p2, m1, m2 = at(u, i), at(u, i + 1), at(slope, i), at(slope, i + 1)
    # outside the record the input is held: no slope there
    m1 = jnp.where((i < 0) | (i > n - 1), 0.0, m1)
    m2 = jnp.where((i + 1 < 0) | (i + 1 > n - 1), 0.0, m2)
    t2, t3 = t * t, t * t * t
    # the cubic Hermite basis: (1, 0) at t = 0 and (0, 1) at t = 1, exactly
    h00, h01 = 2.0 * t3 - 3.0 * t2 + 1.0, 3.0 * t2 - 2.0 * t3
    h10, h11 = t3 - 2.0 * t2 + t, t3 - t2
    return h00 * p1 + h01 * p2 + h10 * m1 + h11 * m2
