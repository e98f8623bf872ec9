"""A static output polynomial after a hysteresis operator: loops that are not odd-symmetric."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, check_finite, check_positive, check_scalar, check_vector
from .base import AbstractHysteresis, AbstractOutputMap


class OutputPolynomial(AbstractOutputMap):
    r"""A hysteresis operator followed by a static polynomial: $y = h + s\sum_{k=2}^{K} a_k (h/s)^k$.

    $h = \mathcal{H}[v]$ is the operator's output.

    The exact operators (PI, Maxwell slip, Bouc–Wen with $n = 1$) give loops that are odd-symmetric about the
    origin; a measured loop often is not (peaks and troughs of different size). A static map after the operator
    keeps it rate-independent and shapes the loop without touching its memory. `scale` $s$ (in the output's unit)
    keeps the coefficients $a_k$ of order one; choose it near the output's amplitude. It is an array leaf, saved
    with the model, but a convention rather than a parameter: fit the coefficients, not the scale (with them free,
    it only rescales them).

    The state is the inner operator's (`init`, `step`, `scan` are its own, with the polynomial applied to the
    output), so an initial state or a prehistory works as for the operator alone.

    **Arguments:**

    - `hysteresis`: the operator $\mathcal{H}$ (any `AbstractHysteresis`).
    - `coefficients`: $[a_2, \dots, a_K]$, shape `(K - 1,)`, finite (zeros: the operator unchanged).
    - `scale`: $s > 0$, finite. Default 1.

    **Example:**

    ```python
    op = pj.OutputPolynomial(pj.PrandtlIshlinskii(w, r, w0=1.0), coefficients=[0.01, -0.005], scale=20.0)
    y = op(v)
    ```
    """

    hysteresis: AbstractHysteresis
    coefficients: Array = eqx.field(converter=jnp.asarray)
    scale: Array

    def __init__(self, hysteresis: AbstractHysteresis, coefficients: ArrayLike, scale: ArrayLike = 1.0):
        if not isinstance(hysteresis, AbstractHysteresis):
            raise PiezojaxValueError(
                f"`hysteresis` must be an AbstractHysteresis, got {type(hysteresis).__name__}"
            )
        self.hysteresis = hysteresis
        self.coefficients = check_vector(coefficients, "coefficients")
        self.scale = check_positive(check_scalar(scale, "scale", self.coefficients.dtype, finite=False), "scale")

    def check(self) -> "OutputPolynomial":
        inner = self.hysteresis.check()
        checked = (inner, check_finite(self.coefficients, "coefficients"), check_positive(self.scale, "scale"))
        return eqx.tree_at(lambda m: (m.hysteresis, m.coefficients, m.scale), self, checked)

    def shape(self, h: Array) -> Array:
        """The static map applied to the operator's output `h` (any shape)."""
        scale = self.scale.astype(h.dtype)
        x = h / scale
        powers = x[..., None] ** jnp.arange(2, 2 + self.coefficients.shape[0], dtype=x.dtype)
        return h + scale * jnp.sum(self.coefficients.astype(x.dtype) * powers, axis=-1)
