"""A hysteresis operator times a gain: an operator identified in one unit used in another (volts to charge)."""

import equinox as eqx
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, as_parameter_array, check_finite, check_scalar
from .._dtypes import module_float_dtype
from .base import AbstractHysteresis, AbstractOutputMap


class ScaledHysteresis(AbstractOutputMap):
    r"""$y = g\,\mathcal{H}[v]$: a hysteresis operator followed by a constant gain.

    Paper 001's observer reads its charge hysteresis in coulombs, $Q_V = C_P\,\mathcal{F}_H[V]$, while the operator
    $\mathcal{F}_H$ is identified in volts of $C_P$; the gain keeps the operator's parameters of order one. The
    state is the inner operator's (`init`, `step`, `scan` are its own with the output scaled), so an initial state
    or a prehistory works as for the operator alone, and the operator's own fast loop and derivatives are used.

    **Arguments:**

    - `hysteresis`: the operator $\mathcal{H}$ (any `AbstractHysteresis`).
    - `gain`: $g$, a real, finite scalar.

    **Example:**

    ```python
    charge = pj.ScaledHysteresis(pj.PrandtlIshlinskii(w, r, w0=1.0), gain=1.74e-9)   # C_P * PI[v] in coulombs
    q = charge(v)
    ```
    """

    hysteresis: AbstractHysteresis
    gain: Array

    def __init__(self, hysteresis: AbstractHysteresis, gain: ArrayLike):
        if not isinstance(hysteresis, AbstractHysteresis):
            raise PiezojaxValueError(
                f"`hysteresis` must be an AbstractHysteresis, got {type(hysteresis).__name__}"
            )
        self.hysteresis = hysteresis
        # the inner operator's dtype, strongly typed (no retrace when a fitter swaps in an array)
        self.gain = check_scalar(as_parameter_array(gain, "gain", module_float_dtype(hysteresis)), "gain")

    def shape(self, h: Array) -> Array:
        """$g h$ for the operator's output `h` (any shape)."""
        return self.gain.astype(h.dtype) * h

    def check(self) -> "ScaledHysteresis":
        checked = (self.hysteresis.check(), check_finite(self.gain, "gain"))
        return eqx.tree_at(lambda m: (m.hysteresis, m.gain), self, checked)
