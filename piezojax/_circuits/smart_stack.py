"""Paper 002 (Chen & Li 2014): a preloaded piezo stack with a sensor layer read by a charge amplifier."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    check_component,
    check_positive_param,
    check_scalar_param,
    error_if_not_finite,
    error_if_not_positive,
)
from .._custom_types import Signal, SignalLike
from .._dtypes import param_dtype
from .._hysteresis.base import AbstractHysteresis
from .._linear.transfer_function import TransferFunction
from .base import (
    AbstractCircuit,
    prepare,
)


class SmartStackCircuit(AbstractCircuit):
    r"""Smart piezo stack in a preloaded flexure stage: sensor-layer force read by a charge amplifier (paper 002).

    The actuator part turns the drive $V_a$ into the stack displacement $x_a = f(V_a)$ (eq. 2; `actuator`). The
    stage (Fig. 14) loads the stack; the force on the sensor layer is eq. (3):

    $\dfrac{F_s}{x_a} = \dfrac{(k_s k_e + k_e k_p + k_p k_s) m_e s^2 + k_p k_s c_e s + k_s k_e k_p}
    {(k_p + k_s) m_e s^2 + (k_p + k_s) c_e s + k_s k_e + k_e k_p}
    = \dfrac{k_p k_s}{k_p + k_s} + k_e\,\dfrac{m_e s^2}{m_e s^2 + c_e s + k_e}$

    (the right-hand form is our partial-fraction reading of eq. 3: the series stiffness of stack and preload spring,
    plus the spring force of the stage mass excited through $k_e$, $c_e$; it is what is simulated, as it is well
    conditioned and stays valid when $m_e \to 0$). The charge amplifier gives eq. (1) plus the crosstalk of eq. (7):

    $V_s = \dfrac{d_{33}}{C} F_s + p_c V_a$.

    `d33` is the effective sensor coefficient including the amplifier gain; the paper's calibrated force sensitivity
    is $d_{33}/C = 0.015381$ V/N.

    **Arguments:**

    - `d33` [C/N] > 0; `amplifier_capacitance` $C$ [F] > 0 (104 pF in the paper).
    - `k_p`, `k_s`, `k_e` [N/m] > 0: preload spring, stack and stage stiffness; `m_e` [kg] > 0, `c_e` [N s/m] ≥ 0.
    - `crosstalk`: $p_c$ [V/V], the sensor voltage per actuator volt (negative in the paper), default 0.
    - `actuator`: a `pj.AbstractHysteresis` mapping the drive $V_a$ to $x_a$ [m] (e.g. a `pj.PrandtlIshlinskii` in
      m/V), or `None` (then pass `x_a` to `__call__`).

    ```python
    stack = pj.SmartStackCircuit(1.6e-12, 104e-12, 6.3e6, 5e7, 0.05, 20.0, 2e7, crosstalk=-3e-4)
    v_s = stack(v_a, 1e-4, x_a=x_a)      # sensor voltage [V]
    ```
    """

    d33: Float[Array, ""]
    amplifier_capacitance: Float[Array, ""]
    k_p: Float[Array, ""]
    k_s: Float[Array, ""]
    m_e: Float[Array, ""]
    c_e: Float[Array, ""]
    k_e: Float[Array, ""]
    crosstalk: Float[Array, ""]
    actuator: AbstractHysteresis | None

    def __init__(
        self,
        d33: ArrayLike,
        amplifier_capacitance: ArrayLike,
        k_p: ArrayLike,
        k_s: ArrayLike,
        m_e: ArrayLike,
        c_e: ArrayLike,
        k_e: ArrayLike,
        crosstalk: ArrayLike = 0.0,
        actuator: AbstractHysteresis | None = None,
    ):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((d33, amplifier_capacitance, k_p, k_s, m_e, c_e, k_e, crosstalk,
                                              actuator)))
        self.d33 = check_positive_param(d33, "d33", dtype=dtype)
        self.amplifier_capacitance = check_positive_param(amplifier_capacitance, "amplifier_capacitance", dtype=dtype)
        self.k_p = check_positive_param(k_p, "k_p", dtype=dtype)
        self.k_s = check_positive_param(k_s, "k_s", dtype=dtype)
        self.m_e = check_positive_param(m_e, "m_e", dtype=dtype)
        self.c_e = check_positive_param(c_e, "c_e", allow_zero=True, dtype=dtype)
        self.k_e = check_positive_param(k_e, "k_e", dtype=dtype)
        self.crosstalk = check_scalar_param(crosstalk, "crosstalk", dtype=dtype)
        self.actuator = check_component(actuator, AbstractHysteresis, "actuator", "op(v_a)")

    def check(self) -> "SmartStackCircuit":
        names = ("d33", "amplifier_capacitance", "k_p", "k_s", "m_e", "c_e", "k_e")
        return error_if_not_finite(error_if_not_positive(self, names, allow_zero=("c_e",)), ("crosstalk",))

    def series_stiffness(self) -> Float[Array, ""]:
        r"""$k_p k_s / (k_p + k_s)$, the static gain of eq. (3) [N/m]."""
        return self.k_p * self.k_s / (self.k_p + self.k_s)

    def displacement_sensitivity(self) -> Float[Array, ""]:
        r"""Eq. (9): $x_a / V_s = (k_p + k_s)\,C / (k_p k_s d_{33})$ [m/V] below $\omega_z$, without crosstalk
        (paper: 11.6126 µm/V)."""
        return self.amplifier_capacitance / (self.d33 * self.series_stiffness())

    def zero_frequency(self) -> Float[Array, ""]:
        r"""Eq. (5): the frequency of the zeros of eq. (3), $\omega_z = \sqrt{k_s k_e k_p / (m_e (k_s k_e + k_e k_p
        + k_p k_s))}$ [rad/s]; below it the sensor voltage follows $x_a$ statically (eq. 6)."""
        kp, ks, ke = self.k_p, self.k_s, self.k_e
        return jnp.sqrt(ks * ke * kp / (self.m_e * (ks * ke + ke * kp + kp * ks)))

    def stage_transfer_function(self) -> TransferFunction:
        """Eq. (3) $F_s/x_a$ as printed in the paper (numerator and denominator polynomials in s)."""
        kp, ks, ke, me, ce = self.k_p, self.k_s, self.k_e, self.m_e, self.c_e
        num = jnp.stack([(ks * ke + ke * kp + kp * ks) * me, kp * ks * ce, ks * ke * kp])
        den = jnp.stack([(kp + ks) * me, (kp + ks) * ce, ks * ke + ke * kp])
        return TransferFunction(num, den)

    def _force(self, x_a: Array, dt: Array) -> Array:
        zero = jnp.zeros((), x_a.dtype)
        high_pass = TransferFunction(
            jnp.stack([self.m_e, zero, zero]), jnp.stack([self.m_e, self.c_e, self.k_e])
        )
        # x_a is a continuous displacement: interpolate it linearly (FOH); a held staircase would kick the lightly
        # damped stage at every sample through the high-pass term.
        return self.series_stiffness() * x_a + self.k_e * high_pass.simulate(x_a, dt, hold="foh")

    def sensor_force(self, x_a: SignalLike, dt: ArrayLike) -> Signal:
        """The force on the sensor layer $F_s$ [N] (eq. 3) for the stack displacement `x_a` [m] (linear between
        samples)."""
        m, dt, s = prepare(self, dt, x_a=x_a)
        return m._force(s["x_a"], dt)

    def __call__(self, v_a: SignalLike, dt: ArrayLike, x_a: SignalLike | None = None) -> Signal:
        r"""The sensor voltage $V_s = (d_{33}/C) F_s + p_c V_a$ [V].

        **Arguments:**

        - `v_a`: actuator drive [V], shape `(time,)`.
        - `dt`: sample step [s].
        - `x_a`: stack displacement [m] (same length), or `None` to compute it with `actuator`: the circuit's
          `load` (`AbstractCircuit.__call__`).

        **Returns:** $V_s$, shape `(time,)`.
        """
        m, dt, s = prepare(self, dt, v_a=v_a, x_a=x_a)
        x = s["x_a"]
        if x is None:
            if m.actuator is None:
                raise PiezojaxValueError("`x_a` is required when the circuit has no `actuator`")
            x = m.actuator(s["v_a"])
        return m.d33 / m.amplifier_capacitance * m._force(x, dt) + m.crosstalk * s["v_a"]
