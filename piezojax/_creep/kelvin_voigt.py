"""Kelvin–Voigt creep chain: a static compliance plus a sum of first-order lags."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import (
    PiezojaxValueError,
    as_float_array,
    check_positive,
    check_scalar,
    check_vector,
    common_float_dtype,
)
from .._hysteresis.play import _tangent_or_none
from .base import AbstractCreep


def _foh_psi(x: Array) -> Array:
    r"""$\psi(x) = (x - 1 + e^{-x}) / x^2 = \sum_{n \ge 0} (-x)^n/(n+2)!$, accurate for every $x > 0$.

    The closed form cancels catastrophically for small $x = dt/\tau$ (slow creep, fast sampling), so below 0.5 the
    series (14 terms, truncation < 1e-16) is used.
    """
    small = x < 0.5
    xs = jnp.where(small, x, 0.0)
    coeffs = [1.0]
    for n in range(1, 14):
        coeffs.append(coeffs[-1] / (n + 2))  # 1/(n+2)! relative to 1/2!
    series = jnp.zeros_like(x)
    for c in reversed(coeffs):
        series = series * (-xs) + c
    series = series / 2.0
    xl = jnp.where(small, 1.0, x)
    direct = (xl + jnp.expm1(-xl)) / (xl * xl)
    return jnp.where(small, series, direct)


@jax.custom_jvp
def lag_scan(a: Array, b0: Array, b1: Array, c: Array, u: Array, u_next: Array) -> Array:
    r"""Diagonal first-order lags from rest: $x_{k+1} = a \odot x_k + b_0 \odot u_k + b_1 \odot u^{+}_k$,
    $x_0 = 0$; returns $y_k = c \cdot x_k$ (shape `(time,)`; `a`, `b0`, `b1`, `c`: shape `(lags,)`).

    Derivatives are hand-derived forward sensitivities: one scan computes $X^a = \partial x/\partial a$,
    $X^{b_0}$, $X^{b_1}$ (independent of the number of tangent directions), and the output tangent is
    $\dot y_k = x_k \cdot \dot c
    + \sum_l c_l (X^a_{k,l}\dot a_l + X^{b_0}_{k,l}\dot b_{0,l} + X^{b_1}_{k,l}\dot b_{1,l})$ plus
    the lags applied to the input tangents (a scan of its own, skipped when they are symbolic zeros, i.e. for
    measured inputs). Under `jax.jacfwd` the parameter directions are then a matrix product, not a batched scan body.
    """

    def step(x, uu):
        return a * x + b0 * uu[0] + b1 * uu[1], jnp.sum(c * x)

    _, y = jax.lax.scan(step, jnp.zeros_like(c), jnp.stack([u, u_next], axis=1))
    return y


@functools.partial(lag_scan.defjvp, symbolic_zeros=True)
def _lag_scan_jvp(primals, tangents):
    a, b0, b1, c, u, u_next = primals
    da, db0, db1, dc, du, du_next = (_tangent_or_none(t) for t in tangents)

    def step(carry, uu):
        x, xa, x0, x1 = carry
        uk, uk1 = uu[0], uu[1]
        new = (a * x + b0 * uk + b1 * uk1, a * xa + x, a * x0 + uk, a * x1 + uk1)
        return new, jnp.stack(carry)

    zero = jnp.zeros_like(c)
    _, states = jax.lax.scan(step, (zero, zero, zero, zero), jnp.stack([u, u_next], axis=1))
    x = states[:, 0]  # (time, lags)
    y = x @ c
    # the parameter directions: one product of the (time, 4 * lags) sensitivities with the stacked tangents
    coeffs = [jnp.zeros_like(c) if dc is None else dc]
    for d in (da, db0, db1):
        coeffs.append(jnp.zeros_like(c) if d is None else c * d)
    dy = states.reshape(states.shape[0], -1) @ jnp.concatenate(coeffs)
    if du is not None or du_next is not None:
        du = jnp.zeros_like(u) if du is None else du
        du_next = jnp.zeros_like(u) if du_next is None else du_next

        def tangent_step(z, uu):
            return a * z + b0 * uu[0] + b1 * uu[1], jnp.sum(c * z)

        dy = dy + jax.lax.scan(tangent_step, zero, jnp.stack([du, du_next], axis=1))[1]
    return y, dy


def paired_vectors(a: ArrayLike, name_a: str, b: ArrayLike, name_b: str) -> tuple[Array, Array]:
    """Two 1-D real vectors of the same shape (values checked by the caller), or one error naming both."""
    x, y = check_vector(a, name_a, finite=False), check_vector(b, name_b, finite=False)
    if x.shape != y.shape:
        raise PiezojaxValueError(
            f"`{name_a}` and `{name_b}` must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    return x, y


class KelvinVoigtCreep(AbstractCreep):
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

    def instantaneous_gain(self) -> Array:
        return self._c0(self.stiffnesses.dtype)

    def _simulate(self, u: Array, dt: Array, hold: str) -> Array:
        x = dt / self.time_constants
        a = jnp.exp(-x)
        one_minus_a = -jnp.expm1(-x)
        c = 1 / self.stiffnesses
        # Elementwise products only in the scan body: under jacfwd a (batched) dot_general in a scan body costs
        # ~5 µs per step on XLA:CPU, elementwise ~0.1 µs (measured in experiments/bench_dynamics.py).
        # `lag_scan` carries hand-derived sensitivities: under `jax.jacfwd` its parameter directions are one matrix
        # product instead of a scan body batched over every direction of the whole model.
        if hold == "zoh":
            lagged = lag_scan(a, one_minus_a, jnp.zeros_like(a), c, u, u)
        else:
            b1 = x * _foh_psi(x)
            u_next = jnp.concatenate([u[1:], u[-1:]])  # the last update is never output
            lagged = lag_scan(a, one_minus_a - b1, b1, c, u, u_next)
        return self._c0(u.dtype) * u + lagged
