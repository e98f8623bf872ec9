r"""The first-order lag $1/(1 + \tau s)$ of a sampled signal, from rest: the one implementation in piezojax.

Every lag in the library (the creep blocks `KelvinVoigtCreep` and `LagCreep`, the benches' electronics, the
initial-value columns of `fitting` and the staged identification) is computed here, with one of three conventions
for what a sample means between sampling instants (`hold`):

- `"zoh"`: $u_k$ is held from $t_k$ until $t_{k+1}$ (a DAC's output): $x_{k+1} = a x_k + (1 - a) u_k$, so the
  lagged output at $t_k$ has seen $u_0 \dots u_{k-1}$;
- `"foh"`: $u$ moves linearly from $u_k$ to $u_{k+1}$: $x_{k+1} = a x_k + (1 - a - b) u_k + b\,u_{k+1}$ with
  $b = 1 - \tau(1 - a)/dt$ (evaluated without cancellation);
- `"interval"`: $u_k$ is the mean over $(t_{k-1}, t_k]$ (an integrating ADC, a current; the circuits' sampling
  convention, see `piezojax._circuits.base`): $x_k = a x_{k-1} + (1 - a) u_k$ — the `"zoh"` lag one sample
  earlier.

All are exact for their input, with $a = e^{-dt/\tau}$ and the state at rest before the first sample. `lag_sum` is
the JAX form (hand-derived forward sensitivities: under `jax.jacfwd` the parameter directions are one matrix product
rather than a scan body batched over every direction); `lag_columns` the NumPy form for linear least squares.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy  # submodules (signal, optimize, linalg) load on first use: importing them costs about a second
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError
from .._config import use_parallel_scan
from .._dtypes import common_float_dtype, matmul
from .._hysteresis.play import _tangent_or_none
from .._scans import affine_scan

HOLDS = ("zoh", "foh", "interval")


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

    if use_parallel_scan(u.shape[0]):
        return matmul(_states_parallel(a, b0[None] * u[:, None] + b1[None] * u_next[:, None]), c)

    def step(x, uu):
        return a * x + b0 * uu[0] + b1 * uu[1], jnp.sum(c * x)

    _, y = jax.lax.scan(step, jnp.zeros_like(c), jnp.stack([u, u_next], axis=1))
    return y


def _states_parallel(a: Array, drive: Array) -> Array:
    r"""The states $x_0 = 0, \ldots, x_{time-1}$ of $x_{k+1} = a \odot x_k + d_k$ (`drive`: shape `(time, *lags)`),
    by `affine_scan` (the state each sample meets: the inclusive scan shifted by one sample)."""
    after = affine_scan(a, drive)
    return jnp.concatenate([jnp.zeros_like(after[:1]), after[:-1]])


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
    if use_parallel_scan(u.shape[0]):
        # x first, then its sensitivities X^a (driven by x), X^{b0} (by u), X^{b1} (by u+): one scan of three
        x = _states_parallel(a, b0[None] * u[:, None] + b1[None] * u_next[:, None])
        drive = jnp.stack([x, jnp.broadcast_to(u[:, None], x.shape), jnp.broadcast_to(u_next[:, None], x.shape)], 1)
        states = jnp.concatenate([x[:, None], _states_parallel(a, drive)], axis=1)
    else:
        _, states = jax.lax.scan(step, (zero, zero, zero, zero), jnp.stack([u, u_next], axis=1))
    x = states[:, 0]  # (time, lags)
    y = matmul(x, c)
    # the parameter directions: one product of the (time, 4 * lags) sensitivities with the stacked tangents
    coeffs = [jnp.zeros_like(c) if dc is None else dc]
    for d in (da, db0, db1):
        coeffs.append(jnp.zeros_like(c) if d is None else c * d)
    dy = matmul(states.reshape(states.shape[0], -1), jnp.concatenate(coeffs))
    if du is not None or du_next is not None:
        du = jnp.zeros_like(u) if du is None else du
        du_next = jnp.zeros_like(u) if du_next is None else du_next

        def tangent_step(z, uu):
            return a * z + b0 * uu[0] + b1 * uu[1], jnp.sum(c * z)

        if use_parallel_scan(u.shape[0]):
            dy = dy + matmul(_states_parallel(a, b0[None] * du[:, None] + b1[None] * du_next[:, None]), c)
        else:
            dy = dy + jax.lax.scan(tangent_step, zero, jnp.stack([du, du_next], axis=1))[1]
    return y, dy



def _check_hold(hold: str) -> None:
    if hold not in HOLDS:
        raise PiezojaxValueError(f"`hold` must be one of {HOLDS}, got {hold!r}")


def zoh_lag_coefficients(tau: Array, dt: Array) -> tuple[Array, Array]:
    r"""$a = e^{-dt/\tau}$ and $1 - a$ (as $-\mathrm{expm1}(-dt/\tau)$, without cancellation for slow lags): the
    ZOH lag $x_{k+1} = a x_k + (1 - a) u_k$. Used by `lag_sum`, the creep cells and the benches' per-sample lags."""
    x = dt / tau
    return jnp.exp(-x), -jnp.expm1(-x)


def lag_sum(c: Array, tau: Array, u: Array, dt: Array, hold: str = "zoh") -> Array:
    r"""$\sum_i c_i\,\mathcal{L}_{\tau_i}[u]$: unit-gain first-order lags $1/(1 + \tau_i s)$ of `u`, from rest,
    weighted by `c` (see the module docstring for `hold`).

    **Arguments:** `c`, `tau`: shape `(lags,)` ($\tau_i > 0$, unchecked: callers check their parameters);
    `u`: shape `(time,)`; `dt`: the sample step (scalar); `hold`: `"zoh"`, `"foh"` or `"interval"`.

    **Returns:** shape `(time,)`. Works under `jit`, `vmap`, `jax.jacfwd` and `jax.grad`.
    """
    _check_hold(hold)
    dtype = common_float_dtype(c, tau, u, dt)
    c, tau, u, dt = (jnp.asarray(z, dtype) for z in (c, tau, u, dt))
    a, one_minus_a = zoh_lag_coefficients(tau, dt)
    zero = jnp.zeros_like(a)
    if hold == "zoh":
        return lag_scan(a, one_minus_a, zero, c, u, u)
    if hold == "foh":
        x = dt / tau
        b1 = x * _foh_psi(x)
        u_next = jnp.concatenate([u[1:], u[-1:]])  # the last update is never output
        return lag_scan(a, one_minus_a - b1, b1, c, u, u_next)
    # "interval": the zoh lag of one more sample, read one sample later
    u_ext = jnp.concatenate([u, u[-1:]])
    return lag_scan(a, one_minus_a, zero, c, u_ext, u_ext)[1:]


def lag_columns(u: np.ndarray, dt: float, tau: ArrayLike, hold: str = "zoh") -> np.ndarray:
    r"""`(time, lags)` NumPy columns $\mathcal{L}_{\tau_i}[u]$ (unit gain, from rest): the same lags as
    `lag_sum(c, tau, u, dt, hold)` $= $ `lag_columns(u, dt, tau, hold) @ c`, in float64 by `scipy.signal.lfilter`
    (for linear least squares on long records)."""
    _check_hold(hold)
    u = np.asarray(u, dtype=float)
    tau = np.atleast_1d(np.asarray(tau, dtype=float))
    cols = np.zeros((u.size, tau.size))
    for i, t in enumerate(tau):
        x = dt / t
        a, one_minus_a = np.exp(-x), -np.expm1(-x)
        if hold == "zoh":
            cols[:, i] = scipy.signal.lfilter([0.0, one_minus_a], [1.0, -a], u)
        elif hold == "interval":
            cols[:, i] = scipy.signal.lfilter([one_minus_a], [1.0, -a], u)
        else:
            b1 = float(x * _foh_psi(np.asarray(x)))
            # x_k = a x_{k-1} + (1 - a - b1) u_{k-1} + b1 u_k for k >= 1, and x_0 = 0 (at rest)
            col = scipy.signal.lfilter([b1, one_minus_a - b1], [1.0, -a], u)
            cols[:, i] = col - b1 * u[0] * a ** np.arange(u.size) if u.size else col
    return cols
