"""A linear system given by transfer-function polynomial coefficients (scipy convention)."""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, as_float_array, check_value, check_vector, concrete_or_none
from .._dtypes import common_float_dtype
from .base import AbstractLinearSystem


def normalise_tf(num: ArrayLike, den: ArrayLike) -> tuple[Array, Array]:
    """Validate `num`/`den`, divide both by `den[0]` and left-pad `num` with zeros to the length of `den`."""
    num, den = as_float_array(num, "num"), as_float_array(den, "den")
    dtype = common_float_dtype(num, den)
    with jax.ensure_compile_time_eval():  # a concrete argument stays concrete under `jit`
        num, den = jnp.atleast_1d(num), jnp.atleast_1d(den)
    num = check_vector(num, "num", dtype)
    den = check_vector(den, "den", dtype)
    num_c = concrete_or_none(num)
    if num_c is not None:
        # Leading zeros do not change the degree (scipy strips them too).
        nz = np.flatnonzero(num_c)
        lead = int(nz[0]) if nz.size else num_c.shape[0] - 1
        if num_c.shape[0] - lead <= den.shape[0]:
            num = num[max(0, min(lead, num.shape[0] - den.shape[0])) :] if num.shape[0] > den.shape[0] else num
    den = check_value(den, lambda d: d[0] != 0, "`den` must have a nonzero leading coefficient den[0]")
    if num.shape[0] > den.shape[0]:
        if num_c is None:  # traced: its leading zeros cannot be seen, and they would change the shapes
            raise PiezojaxValueError(
                f"`num` has {num.shape[0]} coefficients, more than the {den.shape[0]} of `den`: a traced `num` (under "
                "`jit`, `vmap` or differentiation) must have at most as many as `den` (drop its leading zeros)"
            )
        raise PiezojaxValueError(
            f"the transfer function must be proper: `num` has degree {num.shape[0] - 1} > "
            f"degree {den.shape[0] - 1} of `den`"
        )
    num = jnp.concatenate([jnp.zeros((den.shape[0] - num.shape[0],), dtype), num])
    return num / den[0], den / den[0]


class TransferFunction(AbstractLinearSystem):
    r"""A SISO transfer function $G(s) = \dfrac{b_0 s^m + \dots + b_m}{a_0 s^n + \dots + a_n}$, $m \le n$.

    Coefficients are highest power first, as in `scipy.signal.TransferFunction` / `lti`. They are stored normalised
    ($a_0 = 1$) with `num` left-padded to the length of `den`.

    The realisation is the controllable canonical form of `scipy.signal.tf2ss`, rescaled in frequency by
    $w = \max_j |a_j|^{1/j}$ (a bound on the pole magnitudes): $A = w\begin{bmatrix}-a_1/w & \cdots & -a_n/w^n\\
    I & 0\end{bmatrix}$, $B = w e_1$, $C_j = (b_j - b_0 a_j)/w^j$, $D = b_0$. The transfer function is unchanged;
    the entries of $A\,dt$ stay of order $w\,dt$ instead of $\max|a_j|\,dt$, which keeps the matrix exponential
    accurate for stiff denominators. Polynomial coefficients are still a poor parametrisation for lightly damped or
    widely spread poles; use `StableTransferFunction` (cascade of sections) for those.

    **Arguments:**

    - `num`: numerator coefficients, 1-D, finite, degree ≤ degree of `den` (leading zeros are ignored; a traced
      `num` has no more coefficients than `den`).
    - `den`: denominator coefficients, 1-D, finite, `den[0] != 0`.

    ```python
    G = pj.TransferFunction([1.0], [1.0, 2 * 0.1 * 10.0, 100.0])  # 1 / (s^2 + 2 s + 100)
    y = G.simulate(jnp.ones(2000), 1e-3)                          # step response
    ```
    """

    num: Float[Array, " n+1"]
    den: Float[Array, " n+1"]

    def __init__(self, num: ArrayLike, den: ArrayLike):
        self.num, self.den = normalise_tf(num, den)

    @property
    def order(self) -> int:
        return self.den.shape[0] - 1

    def state_space(self):
        # coefficients replaced after __init__ (`eqx.tree_at`) are checked here, one check for both
        num, den = check_value(
            (self.num, self.den),
            lambda p: jnp.stack([jnp.all(jnp.isfinite(p[0])), jnp.all(jnp.isfinite(p[1])), p[1][0] != 0]),
            [
                "`num` contains NaN or infinite values",
                "`den` contains NaN or infinite values",
                "`den` must have a nonzero leading coefficient den[0]",
            ],
        )
        dtype = den.dtype
        n = den.shape[0] - 1
        D = num[0]
        if n == 0:
            return jnp.zeros((0, 0), dtype), jnp.zeros((0,), dtype), jnp.zeros((0,), dtype), D
        a = den[1:]
        c = num[1:] - D * a
        powers = jnp.arange(1, n + 1, dtype=dtype)
        # w differentiated like A, B, C (the realisation, and a state scanned with it, depend on it, although the
        # output does not: a similarity transform); a zero coefficient is kept out of the power (d|a|^(1/j)/da is
        # infinite at 0, and 0 * inf would make the derivative NaN)
        nonzero = a != 0
        w = jnp.max(jnp.where(nonzero, jnp.abs(jnp.where(nonzero, a, 1.0)) ** (1 / powers), 0.0))
        w = jnp.where(w > 0, w, jnp.ones((), dtype))
        wp = w**powers
        A = jnp.zeros((n, n), dtype).at[0, :].set(-a / wp * w)
        A = A + jnp.diag(jnp.full((n - 1,), w, dtype), -1)
        B = jnp.zeros((n,), dtype).at[0].set(w)
        C = c / wp
        return A, B, C, D

    def transfer_function(self) -> tuple[Float[Array, " n+1"], Float[Array, " n+1"]]:
        """The (normalised, padded) coefficients `(num, den)`."""
        return self.num, self.den
