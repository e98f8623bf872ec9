"""Analog Butterworth low-pass filters."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._checks import PiezojaxValueError, check_scalar, check_value
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
