"""Paper 000 (Bafumba Liseli et al. 2018): displacement observer with dynamic-impedance correction."""

from typing import ClassVar

import equinox as eqx
import jax
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    check_positive_param,
    check_scalar_param,
    error_if_not_finite,
    error_if_not_positive,
)
from .._circuits.base import (
    prepare,
    running_integral,
)
from .._custom_types import Signal, SignalLike
from .._dtypes import param_dtype
from .._linear.base import AbstractLinearSystem
from .base import AbstractObserver, Estimate


class DynamicImpedanceObserver(AbstractObserver):
    r"""Displacement observer of paper 000: feedthrough cancellation, impedance correction $\gamma$, then $G(s)$.

    1. Deformation charge by numerical integration with static feedthrough cancellation (eq. 5):
       $Q_\delta(t) = \int_0^t \left(-\frac{V_{out}}{R_f} - I_{bias}\right)dt - C_r V_{in}(t)$
       (the $C_r\,dV_{in}/dt$ term integrated analytically, from rest).
    2. Transduced force (eq. 9): $F_t = \alpha V_{in} + \beta\,(Q_\delta + \gamma V_{in})$.
    3. Displacement: $\hat\delta = G(s)\,F_t$ (a 3rd-order transfer function in the paper).

    With $\gamma = 0$ this is the static-impedance observer the paper compares against (`static_impedance()`).
    It inverts `TransimpedanceCircuit` exactly: with the circuit's $R_f, I_{bias}, C_r, \gamma$,
    $Q_\delta + \gamma V_{in}$ is the creep charge $Q_c$ sample for sample.

    **Arguments:**

    - `feedback_resistance` $R_f > 0$ [Ω], `capacitance` $C_r > 0$ [F], `gamma` $\ge 0$ [F], `bias_current` [A].
    - `alpha` (0.8971 in the paper) and `beta` (6.9067e7 in the paper), eq. (10)–(11).
    - `dynamics`: $G(s)$, a `pj.AbstractLinearSystem` from $F_t$ to displacement [m per unit of $F_t$].
    - `hold`: how $F_t$ is held between samples when simulating $G$ (`"zoh"` default, or `"foh"`).
    - `offset` [m]: added to the displacement estimate (the zero of the displacement sensor it is compared with).

    ```python
    G = pj.TransferFunction([1e-7 * 1e9], [1.0, 2e3, 2e6, 1e9])
    obs = pj.DynamicImpedanceObserver(1e6, 4.2e-9, 0.66e-9, 0.0, 0.8971, 6.9067e7, G)
    est = obs(v_in, v_out, 1e-3)         # est.displacement [m]
    ```
    """

    estimates: ClassVar[tuple[str, ...]] = ("displacement",)

    feedback_resistance: Float[Array, ""]
    capacitance: Float[Array, ""]
    gamma: Float[Array, ""]
    bias_current: Float[Array, ""]
    alpha: Float[Array, ""]
    beta: Float[Array, ""]
    dynamics: AbstractLinearSystem
    offset: Float[Array, ""]
    hold: str = eqx.field(static=True)

    def __init__(
        self,
        feedback_resistance: ArrayLike,
        capacitance: ArrayLike,
        gamma: ArrayLike,
        bias_current: ArrayLike,
        alpha: ArrayLike,
        beta: ArrayLike,
        dynamics: AbstractLinearSystem,
        hold: str = "zoh",
        *,
        offset: ArrayLike = 0.0,
    ):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((feedback_resistance, capacitance, gamma, bias_current, alpha, beta,
                                              dynamics, hold, offset)))
        self.feedback_resistance = check_positive_param(feedback_resistance, "feedback_resistance", dtype=dtype)
        self.capacitance = check_positive_param(capacitance, "capacitance", dtype=dtype)
        self.gamma = check_positive_param(gamma, "gamma", allow_zero=True, dtype=dtype)
        self.bias_current = check_scalar_param(bias_current, "bias_current", dtype=dtype)
        self.alpha = check_scalar_param(alpha, "alpha", dtype=dtype)
        self.beta = check_scalar_param(beta, "beta", dtype=dtype)
        if not isinstance(dynamics, AbstractLinearSystem):
            raise PiezojaxValueError(
                f"`dynamics` must be a piezojax linear system (G(s)), got {type(dynamics).__name__}"
            )
        self.dynamics = dynamics
        if hold not in ("zoh", "foh"):
            raise PiezojaxValueError(f'`hold` must be "zoh" or "foh", got {hold!r}')
        self.hold = hold
        self.offset = check_scalar_param(offset, "offset", dtype=dtype)

    def check(self) -> "DynamicImpedanceObserver":
        m = error_if_not_positive(self, ("feedback_resistance", "capacitance", "gamma"), allow_zero=("gamma",))
        return error_if_not_finite(m, ("bias_current", "alpha", "beta", "offset"))

    def static_impedance(self) -> "DynamicImpedanceObserver":
        """The same observer with $\\gamma = 0$ (static feedthrough cancellation only)."""
        return eqx.tree_at(lambda o: o.gamma, self, self.gamma * 0)

    def _charge(self, v_in: Array, v_out: Array, dt: Array) -> Array:
        return running_integral(v_out, dt, -1 / self.feedback_resistance, -self.bias_current) - self.capacitance * v_in

    def deformation_charge(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike) -> Signal:
        r"""$Q_\delta$ of eq. (5) [C] from the drive `v_in` and amplifier output `v_out`."""
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        return m._charge(s["v_in"], s["v_out"], dt)

    def transduced_force(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike) -> Signal:
        r"""$F_t = \alpha V_{in} + \beta (Q_\delta + \gamma V_{in})$ of eq. (9)."""
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        v = s["v_in"]
        return m.alpha * v + m.beta * (m._charge(v, s["v_out"], dt) + m.gamma * v)

    def __call__(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike) -> Estimate:
        r"""Estimated displacement $\hat\delta = G(s) F_t$ + `offset` (no force estimate: the paper's $F_{ext} = 0$).

        **Arguments:**

        - `v_in`: drive voltage [V], shape `(time,)`; `v_out`: transimpedance output [V], same length.
        - `dt`: sample step [s].

        **Returns:** an `Estimate` with `displacement` [m] and `force=None`.
        """
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        v = s["v_in"]
        f_t = m.alpha * v + m.beta * (m._charge(v, s["v_out"], dt) + m.gamma * v)
        return Estimate(displacement=m.dynamics.simulate(f_t, dt, hold=m.hold) + m.offset)
