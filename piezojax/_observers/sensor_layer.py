"""Paper 002 (Chen & Li 2014): displacement and force from the sensor layer of a smart piezo stack."""

from collections.abc import Mapping
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
)
from .._custom_types import AbstractCell, SignalLike
from .._dtypes import param_dtype
from .base import AbstractObserver, Estimate


class SensorLayerObserver(AbstractObserver, AbstractCell):
    r"""Displacement (eq. 8–9) and force (eq. 1) of a smart piezo stack from its sensor voltage (paper 002).

    Quasi-static (below the stage zero $\omega_z$, eq. 5) inversion of eq. (8),
    $V_s = \frac{k_s k_p}{k_s + k_p}\frac{d_{33}}{C} x_a + p_c V_a$:

    $\hat x_a = \dfrac{(k_p + k_s)\,C}{k_p k_s\,d_{33}}\,(V_s - p_c V_a)$,
    $\quad \hat F_s = \dfrac{C}{d_{33}}(V_s - p_c V_a)$.

    With $p_c = 0$ (`without_crosstalk()`) this is the paper's eq. (9), which omits the crosstalk term.
    Calibrated values in the paper: $d_{33}/C = 0.015381$ V/N and $(k_p + k_s) C/(k_p k_s d_{33}) = 11.6126$ µm/V.

    **Arguments:**

    - `d33` [C/N] > 0, `amplifier_capacitance` $C$ [F] > 0, `k_p`, `k_s` [N/m] > 0, `crosstalk` $p_c$ [V/V].
    - `offset` [m]: added to the displacement estimate (the zero of the displacement sensor it is compared with).

    ```python
    obs = pj.SensorLayerObserver(1.6e-12, 104e-12, 6.3e6, 5e7, crosstalk=-3e-4)
    est = obs(v_a, v_s, 1e-4)            # est.displacement [m], est.force [N]
    ```
    """

    estimates: ClassVar[tuple[str, ...]] = ("displacement", "force")

    d33: Float[Array, ""]
    amplifier_capacitance: Float[Array, ""]
    k_p: Float[Array, ""]
    k_s: Float[Array, ""]
    crosstalk: Float[Array, ""]
    offset: Float[Array, ""]

    def __init__(self, d33: ArrayLike, amplifier_capacitance: ArrayLike, k_p: ArrayLike, k_s: ArrayLike,
                 crosstalk: ArrayLike = 0.0, *, offset: ArrayLike = 0.0):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((d33, amplifier_capacitance, k_p, k_s, crosstalk, offset)))
        self.d33 = check_positive_param(d33, "d33", dtype=dtype)
        self.amplifier_capacitance = check_positive_param(amplifier_capacitance, "amplifier_capacitance", dtype=dtype)
        self.k_p = check_positive_param(k_p, "k_p", dtype=dtype)
        self.k_s = check_positive_param(k_s, "k_s", dtype=dtype)
        self.crosstalk = check_scalar_param(crosstalk, "crosstalk", dtype=dtype)
        self.offset = check_scalar_param(offset, "offset", dtype=dtype)

    def check(self) -> "SensorLayerObserver":
        m = error_if_not_positive(self, ("d33", "amplifier_capacitance", "k_p", "k_s"))
        return error_if_not_finite(m, ("crosstalk", "offset"))

    def without_crosstalk(self) -> "SensorLayerObserver":
        """The paper's eq. (9): the same observer with $p_c = 0$."""
        return eqx.tree_at(lambda o: o.crosstalk, self, self.crosstalk * 0)

    def _estimate(self, v_in, v_out):
        force = self.amplifier_capacitance / self.d33 * (v_out - self.crosstalk * v_in)
        return force * (self.k_p + self.k_s) / (self.k_p * self.k_s) + self.offset, force

    def init(self) -> tuple[()]:
        """The observer as a cell for `pj.closed_loop`: it is static, so its state is empty."""
        return ()

    def step(self, state: tuple[()], channels: Mapping[str, Array]) -> tuple[tuple[()], Array]:
        r"""The displacement estimate $\hat x_a$ [m] from one sample of the channels `v_in` and `v_out`."""
        missing = [c for c in ("v_in", "v_out") if c not in channels]
        if missing:
            raise PiezojaxValueError(f"the sensor-layer observer needs the channels {missing}, got {sorted(channels)}")
        return state, self._estimate(channels["v_in"], channels["v_out"])[0]

    def __call__(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike = 1.0) -> Estimate:
        r"""Estimates from the actuator drive `v_in` ($V_a$) and sensor voltage `v_out` ($V_s$), same length.

        `dt` is accepted for a uniform observer interface; the estimate is static.

        **Returns:** an `Estimate` with `displacement` $\hat x_a$ + `offset` [m] and `force` $\hat F_s$ [N].
        """
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        displacement, force = m._estimate(s["v_in"], s["v_out"])
        return Estimate(displacement=displacement, force=force)
