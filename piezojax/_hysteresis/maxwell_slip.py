r"""The Maxwell-slip operator: elasto-slide elements in parallel (paper 003 §3.3.1, after Goldfarb & Celanovic)."""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import PiezojaxValueError, check_positive, check_same_shape, check_scalar, check_vector
from .._custom_types import ScalarLike, VectorLike
from .._dtypes import matmul, param_dtype
from .._parametrisation import setting
from .base import AbstractHysteresis, root_finding_inverse
from .play import check_smoothing, error_if_bad_smoothing, run_exact_or_smooth, stop_update
from .prandtl_ishlinskii import PrandtlIshlinskii


class MaxwellSlip(AbstractHysteresis):
    r"""The Maxwell-slip hysteresis model: $n$ spring + Coulomb-slider elements in parallel, driven by one input.

    Mechanical form (paper 003 §3.3.1, Fig. 11–13, eq. 25–26): element $i$ is a spring of stiffness $k_i$ holding a
    massless block of breakaway force $f_i$; with input displacement $x$ and block position $x_{b,i}$ its force is
    $F_i = k_i (x - x_{b,i})$ while $|k_i (x - x_{b,i})| < f_i$ (stick), and the block slides so that
    $F_i = \pm f_i$ otherwise. The spring elongation is therefore the stop operator of threshold $r_i = f_i / k_i$,
    and

    $F = \sum_i F_i = \sum_i k_i\, S_{f_i/k_i}[x]$,

    which is the Prandtl–Ishlinskii operator with $w_0 = \sum_i k_i$, weights $-k_i$ and thresholds $f_i/k_i$.

    Electrical analogue (paper 003 eq. 29–32, the voltage–charge hysteresis of the actuator; eq. 27–28 build the
    elements from the rising curve; the equations are images in our copy of the thesis, so this is the
    Goldfarb–Celanovic form the text describes): the input is the
    charge $q$, element $i$ is a capacitor $C_i$ with breakaway voltage $v_i$ and "slid" charge $q_{b,i}$, its
    voltage is $V_i = (q - q_{b,i})/C_i$ clamped at $\pm v_i$, and the output is the hysteresis voltage
    $V_H = \sum_i V_i$. So `stiffness` $= 1/C_i$ (in V/C), `breakaway` $= v_i$ (in V), input $q$ (in C) and output
    $V_H$ (in V), with charge thresholds $r_i = C_i v_i$; `MaxwellSlip.electrical(capacitances, breakaway_voltages)`
    builds it.

    All elements start relaxed (input 0, zero force). With `smoothing` $s > 0$ each element uses the smooth
    rate-independent law of `play_step` (boundary layer $s f_i/k_i$). Works under `jit`, `vmap`, `jax.grad`,
    `jax.jacfwd`.

    **Arguments:**

    - `stiffness`: $k_i > 0$ (finite), shape `(n,)`.
    - `breakaway`: $f_i \geq 0$ (finite), shape `(n,)`, any order.
    - `smoothing`: relative smoothing $s \geq 0$ (array field); 0 = exact.

    **Returns:** called on a signal of shape `(time,)`, the total force (or $V_H$), shape `(time,)`.

    ```python
    gms = MaxwellSlip(jnp.array([2.0, 1.0]), jnp.array([1.0, 2.0]))
    force = gms(jnp.array([0.25, 1.0, 3.0, 0.0]))  # [0.75, 2.0, 3.0, -2.0]
    ```
    """

    stiffness: Float[Array, " n"]
    breakaway: Float[Array, " n"]
    smoothing: Float[Array, ""] = setting()

    def __init__(self, stiffness: VectorLike, breakaway: VectorLike, smoothing: ScalarLike = 0.0):
        dtype = param_dtype(stiffness, breakaway, smoothing)
        self.stiffness = check_vector(stiffness, "stiffness", dtype)
        self.breakaway = check_vector(breakaway, "breakaway", dtype)
        if self.stiffness.shape != self.breakaway.shape:
            raise PiezojaxValueError(
                f"`stiffness` and `breakaway` must have the same shape, got {tuple(self.stiffness.shape)} and "
                f"{tuple(self.breakaway.shape)}"
            )
        self.stiffness = check_positive(self.stiffness, "stiffness")
        self.breakaway = check_positive(self.breakaway, "breakaway", allow_zero=True)
        self.smoothing = check_smoothing(smoothing, dtype)

    @classmethod
    def electrical(
        cls, capacitances: VectorLike, breakaway_voltages: VectorLike, smoothing: ScalarLike = 0.0
    ) -> "MaxwellSlip":
        r"""The electrical Maxwell-slip model (input charge $q$, output $V_H$): `stiffness` $= 1/C_i$.

        **Arguments:**

        - `capacitances`: $C_i > 0$ in F, shape `(n,)`.
        - `breakaway_voltages`: $v_i \geq 0$ in V, shape `(n,)`.
        - `smoothing`: as for `MaxwellSlip`.

        **Returns:** the `MaxwellSlip` operator mapping charge to hysteresis voltage.
        """
        dtype = param_dtype(capacitances, breakaway_voltages, smoothing)
        c = check_vector(capacitances, "capacitances", dtype)
        c = check_positive(c, "capacitances")
        return cls(1 / c, breakaway_voltages, smoothing)

    @property
    def thresholds(self) -> Array:
        r"""The input thresholds $r_i = f_i / k_i$ (displacement, or charge $C_i v_i$) at which each element slips."""
        return self.breakaway / self.stiffness

    def as_prandtl_ishlinskii(self, linear: ScalarLike = 0.0) -> PrandtlIshlinskii:
        r"""The same operator plus a linear term, $\ell x + F[x]$, as a `PrandtlIshlinskii` (with the same `smoothing`).

        $F = \sum_i k_i S_{r_i}[x] = (\sum_i k_i)\,x - \sum_i k_i P_{r_i}[x]$ (stop = input − play), so the PI form
        has $w_0 = \ell + \sum_i k_i$, weights $-k_i$ and thresholds $r_i = f_i/k_i$, sorted ascending. It gives
        the analytic inverse (paper 003 inverts the electrical model, where the linear capacitance $C$ adds
        $\ell = 1/C$ to $V_H(q)$: $V = q/C + V_H(q)$):
        `ms.as_prandtl_ishlinskii(linear).inverse()`. That inverse needs $\ell > 0$ (alone, the Maxwell slip
        saturates at $\sum_i f_i$ and has no inverse beyond it: use `inverse(lower, upper)`), distinct thresholds
        (elements with equal $f_i/k_i$ must be merged: PI thresholds are strictly ascending) and `smoothing` = 0.

        **Arguments:**

        - `linear`: $\ell$, a finite scalar (default 0).

        **Returns:** the `PrandtlIshlinskii` operator, equal to `linear * x + self(x)` for every input.
        """
        linear = check_scalar(linear, "linear", self.stiffness.dtype)
        order = jnp.argsort(self.thresholds)
        k = self.stiffness[order]
        return PrandtlIshlinskii(-k, self.thresholds[order], w0=linear + jnp.sum(k), smoothing=self.smoothing)

    def check(self) -> "MaxwellSlip":
        check_same_shape(self.stiffness, "stiffness", self.breakaway, "breakaway")
        k, f = check_positive(self.stiffness, "stiffness"), check_positive(self.breakaway, "breakaway", allow_zero=True)
        return eqx.tree_at(
            lambda m: (m.stiffness, m.breakaway, m.smoothing), self, (k, f, error_if_bad_smoothing(self.smoothing))
        )

    zero_at_rest: ClassVar[bool | None] = True

    def init(self) -> tuple[Array, Array]:
        """Relaxed state `(previous input, spring elongations) = (0, 0)`."""
        dtype = self.stiffness.dtype
        return jnp.zeros((), dtype), jnp.zeros(self.stiffness.shape, dtype)

    def step(self, state, x):
        return self._step(state, x, None)

    def _run(self, state, signal):
        # The exact or smooth loop is chosen outside the scan (see `run_exact_or_smooth`).
        return run_exact_or_smooth(self, state, signal)

    def _step(self, state, x, exact):
        x_prev, z = state
        z = stop_update(z, x - x_prev, self.thresholds, self.smoothing, exact)
        return (x, z), matmul(self.stiffness, z)

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        return root_finding_inverse(self, lower, upper, max_iterations)
