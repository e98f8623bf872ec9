"""Analog Butterworth low-pass filters."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, check_scalar, check_value
from .._config import use_parallel_scan
from .stable import StableTransferFunction


def butterworth(order: int, cutoff: ArrayLike) -> StableTransferFunction:
    r"""The analog Butterworth low-pass filter of `order` N and cutoff $\omega_c$ (rad/s).

    $|G(j\omega)|^2 = 1/(1 + (\omega/\omega_c)^{2N})$; poles $\omega_c e^{j\pi(2k + N - 1)/(2N)}$, $k = 1..N$:
    pairs with $\omega = \omega_c$, $\zeta_k = \sin\!\big(\pi(2k - 1)/(2N)\big)$, $k = 1..\lfloor N/2\rfloor$, and a
    real pole $-\omega_c$ when N is odd. Coefficients equal `scipy.signal.butter(N, cutoff, analog=True)`.

    Returned as a DC-normalised all-pole `StableTransferFunction` (gain 1), so `cutoff` stays a differentiable leaf
    of `omega` and `poles`. Discretise it exactly with `.discretise(dt)` / `.simulate(u, dt)`.

    **Arguments:**

    - `order`: N ≥ 1 (a Python int).
    - `cutoff`: the -3 dB angular frequency $\omega_c > 0$ in rad/s (pass $2\pi f_c$ for $f_c$ in Hz).

    **Returns:** a `StableTransferFunction`.

    ```python
    lp = pj.butterworth(3, 2 * jnp.pi * 100.0)   # paper 001's 3rd-order low-pass at 100 Hz
    y = lp.simulate(u, 1e-4)
    ```
    """
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise PiezojaxValueError(f"`order` must be an integer >= 1, got {order!r}")
    cutoff = check_value(
        check_scalar(cutoff, "cutoff", finite=False),
        lambda c: jnp.isfinite(c) & (c > 0),
        "`cutoff` must be a finite, positive angular frequency (rad/s)",
    )
    dtype = cutoff.dtype
    n2 = order // 2
    zeta = jnp.asarray([math.sin(math.pi * (2 * k - 1) / (2 * order)) for k in range(1, n2 + 1)], dtype)
    omega = cutoff * jnp.ones((n2,), dtype)
    poles = -cutoff * jnp.ones((order % 2,), dtype)
    return StableTransferFunction(jnp.ones((), dtype), omega, zeta, poles)


def butterworth_zoh(order: int, cutoff: Array, u: Array, dt: Array) -> Array:
    r"""`butterworth(order, cutoff).simulate(u, dt)` (ZOH, from rest) in modal form: one scan of $N$ decoupled
    first-order recurrences instead of a dense $N \times N$ state update.

    With $s = \omega_c \tilde s$ the filter is $1/\prod_k(\tilde s - q_k)$, $q_k = e^{j\pi(2k + N - 1)/(2N)}$ on the
    unit circle, distinct and at least $2\sin(\pi/2N)$ apart, so its partial fractions
    $\sum_k \tilde r_k/(\tilde s - q_k)$, $\tilde r_k = 1/\prod_{j \ne k}(q_k - q_j)$, are well conditioned for every
    cutoff: $\tilde r_k$ and $q_k$ are constants, and only $z = \omega_c\,dt$ enters the recurrence. Mode $k$ is
    $\dot x_k = \omega_c(q_k x_k + u)$, exactly $x_{k+1} = a_k x_k + b_k u_k$ with $a_k = e^{q_k z}$,
    $b_k = (a_k - 1)/q_k = \bar q_k (a_k - 1)$, and $y_k = \sum_k \tilde r_k x_k$ (a conjugate pair as one complex
    mode, $2\,\mathrm{Re}$, written in real arithmetic; $a_k - 1$ without cancellation for small $z$). Accurate to
    rounding at the scale of the input (tested against the closed-form step response for $N \le 8$, and for
    $z = 10^{-4}$ over $6\cdot10^4$ samples); while the filter has barely responded ($\omega_c t \ll 1$) its tiny
    output is the difference of the modes', so its relative accuracy is lower there than the cascade's.

    Why: under `jax.jacfwd` every parameter direction runs through the filter (the observer's force term); the
    modal update costs about half the dense one per direction (measured in `experiments.bench_observer`). Where
    `piezojax.set_parallel_scans` chooses the parallel form, the cascade realisation's associative scan is used.

    **Arguments:** `order` $N \ge 1$ (a Python int); `cutoff` $\omega_c$ [rad/s] and `dt` [s], scalars $> 0$;
    `u`: shape `(time,)`. Unchecked: callers check their parameters and signals.

    **Returns:** shape `(time,)`, in `u`'s dtype.
    """
    dtype = u.dtype
    if use_parallel_scan(u.shape[0]):
        return butterworth(order, cutoff.astype(dtype)).simulate(u, dt)
    q = np.exp(1j * np.pi * (2 * np.arange(1, order + 1) + order - 1) / (2 * order))
    r = np.array([1 / np.prod([q[k] - q[j] for j in range(order) if j != k]) for k in range(order)])
    z = (cutoff * dt).astype(dtype)
    real_mode = order % 2 == 1  # q = -1 at k = (N + 1) / 2
    pairs = range(order // 2)  # q_k in the upper half-plane, k = 1 .. N/2 (its conjugate is mode N + 1 - k)
    coefficients = []
    for k in pairs:
        qr, qi = float(q[k].real), float(q[k].imag)  # Python floats: weakly typed beside float32
        sz, wz = qr * z, qi * z
        growth = jnp.exp(sz)
        # a - 1 = (e^{sz} cos wz - 1) + j e^{sz} sin wz, with e^{sz} cos wz - 1 = expm1(sz) cos wz - 2 sin^2(wz/2)
        am1_re = jnp.expm1(sz) * jnp.cos(wz) - 2 * jnp.sin(wz / 2) ** 2
        am1_im = growth * jnp.sin(wz)
        b_re = qr * am1_re + qi * am1_im  # conj(q) (a - 1)
        b_im = qr * am1_im - qi * am1_re
        coefficients.append((am1_re, am1_im, b_re, b_im, 2 * float(r[k].real), -2 * float(r[k].imag)))
    if real_mode:
        b_real = -jnp.expm1(-z)  # a - 1 = -b and (a - 1)/q = b, with q = -1
        c_real = float(r[order // 2].real)

    # x + ((a - 1) x + b u): the increment form, as `DiscreteStateSpace.step` (a near 1 for a slow filter: a's
    # rounding would otherwise be integrated over the record)
    def step(state, uk):
        y = jnp.zeros((), dtype)
        new = []
        for (d_re, d_im, b_re, b_im, c_re, c_im), (x_re, x_im) in zip(coefficients, state[0]):
            y = y + c_re * x_re + c_im * x_im
            new.append((x_re + (d_re * x_re - d_im * x_im + b_re * uk),
                        x_im + (d_re * x_im + d_im * x_re + b_im * uk)))
        x_real = state[1]
        if real_mode:
            y = y + c_real * x_real
            x_real = x_real + b_real * (uk - x_real)
        return (new, x_real), y

    zero = jnp.zeros((), dtype)
    return jax.lax.scan(step, ([(zero, zero) for _ in pairs], zero), u)[1]
