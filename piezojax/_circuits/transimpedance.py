"""Paper 000 (Bafumba Liseli et al. 2018): the piezo current read by a transimpedance amplifier."""

import jax
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    check_component,
    check_positive_param,
    check_scalar_param,
    error_if_not_finite,
    error_if_not_positive,
)
from .._creep.base import AbstractCreep
from .._custom_types import Signal, SignalLike
from .._dtypes import param_dtype
from .._linear.base import AbstractLinearSystem
from .base import (
    AbstractCircuit,
    interval_current,
    prepare,
)


class TransimpedanceCircuit(AbstractCircuit):
    r"""Transimpedance read-out of a piezo actuator whose capacitance drops with deformation (paper 000, eq. 3–9).

    Charge model (our reading of §II–III of the paper): the electrodes carry the feedthrough charge of the
    undeformed capacitance, minus the capacitance change $\gamma$ that appears as soon as the actuator deforms
    (Table I: the jump of $Q_\delta$ at a step is $-\gamma V_{in}$ for every step height), plus the deformation
    charge that creeps after the step (the "transduced direct effect", Fig. 6 and 9):

    $Q_{pzt} = (C_r - \gamma)\,V_{in} + Q_c$, $\quad Q_c = \mathcal{C}[V_{in}]$ (a creep block in C/V, 0 at $t=0^+$),

    so the deformation charge of eq. (5) is $Q_\delta = Q_{pzt} - C_r V_{in} = -\gamma V_{in} + Q_c$. The amplifier
    gives (eq. 3) $V_{out} = -R_f\,(I_{pzt} + I_{bias})$ with $I_{pzt} = dQ_{pzt}/dt$.

    Samples follow the convention of `piezojax._circuits.base`: `v_out[k]` is the mean over $(t_{k-1}, t_k]$, the
    record starts from rest, so $-dt\sum_{j\le k}(V_{out,j}/R_f + I_{bias}) = Q_{pzt}(t_k)$ exactly.

    **Arguments:**

    - `feedback_resistance`: $R_f > 0$ [Ω].
    - `capacitance`: $C_r > 0$, capacitance without deformation and field [F].
    - `gamma`: $\gamma \ge 0$, capacitance drop under deformation [F] (0.66 nF in the paper).
    - `bias_current`: $I_{bias}$ [A], default 0.
    - `creep`: the deformation-charge creep $\mathcal{C}$ (e.g. `pj.KelvinVoigtCreep(..., k0=None)` or a
      `pj.TransferFunction` with zero high-frequency gain: a `pj.AbstractCreep` or `pj.AbstractLinearSystem`, called as
      `creep(v_in, dt)`), or `None` for none.

    ```python
    circuit = pj.TransimpedanceCircuit(1e6, 4.2e-9, 0.66e-9,
                                       creep=pj.KelvinVoigtCreep([1 / 2e-10], [20.0], k0=None))
    v_out = circuit(v_in, 1e-3)          # V_out samples
    q = circuit.charge(v_in, 1e-3)       # Q_pzt samples
    ```
    """

    feedback_resistance: Float[Array, ""]
    capacitance: Float[Array, ""]
    gamma: Float[Array, ""]
    bias_current: Float[Array, ""]
    creep: AbstractCreep | AbstractLinearSystem | None

    def __init__(
        self,
        feedback_resistance: ArrayLike,
        capacitance: ArrayLike,
        gamma: ArrayLike = 0.0,
        bias_current: ArrayLike = 0.0,
        creep: AbstractCreep | AbstractLinearSystem | None = None,
    ):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((feedback_resistance, capacitance, gamma, bias_current, creep)))
        self.feedback_resistance = check_positive_param(feedback_resistance, "feedback_resistance", dtype=dtype)
        self.capacitance = check_positive_param(capacitance, "capacitance", dtype=dtype)
        self.gamma = check_positive_param(gamma, "gamma", allow_zero=True, dtype=dtype)
        self.bias_current = check_scalar_param(bias_current, "bias_current", dtype=dtype)
        self.creep = check_component(creep, (AbstractCreep, AbstractLinearSystem), "creep", "creep(v, dt)")

    def check(self) -> "TransimpedanceCircuit":
        m = error_if_not_positive(self, ("feedback_resistance", "capacitance", "gamma"), allow_zero=("gamma",))
        return error_if_not_finite(m, ("bias_current",))

    def _charge(self, v_in: Array, dt: Array) -> Array:
        q = (self.capacitance - self.gamma) * v_in
        if self.creep is not None:
            q = q + self.creep(v_in, dt)
        return q

    def charge(self, v_in: SignalLike, dt: ArrayLike) -> Signal:
        r"""The electrode charge $Q_{pzt}(t_k)$ [C] for the drive `v_in` (1-D, from rest) sampled with step `dt`."""
        m, dt, s = prepare(self, dt, v_in=v_in)
        return m._charge(s["v_in"], dt)

    def deformation_charge(self, v_in: SignalLike, dt: ArrayLike) -> Signal:
        r"""The true deformation charge $Q_\delta = Q_{pzt} - C_r V_{in} = -\gamma V_{in} + Q_c$ [C]."""
        m, dt, s = prepare(self, dt, v_in=v_in)
        return m._charge(s["v_in"], dt) - m.capacitance * s["v_in"]

    def current(self, v_in: SignalLike, dt: ArrayLike) -> Signal:
        r"""The piezo current $I_{pzt}$ [A], as interval means $(Q_k - Q_{k-1})/dt$ from rest."""
        m, dt, s = prepare(self, dt, v_in=v_in)
        return interval_current(m._charge(s["v_in"], dt), dt)

    def __call__(self, v_in: SignalLike, dt: ArrayLike, load: SignalLike | None = None) -> Signal:
        r"""The amplifier output $V_{out} = -R_f (I_{pzt} + I_{bias})$ [V] for the drive `v_in` [V], step `dt` [s].

        The output depends on the drive only: a `load` signal raises a `PiezojaxValueError`."""
        if load is not None:
            raise PiezojaxValueError(
                "`load`: TransimpedanceCircuit has no mechanical input (its output depends on the drive only)"
            )
        m, dt, s = prepare(self, dt, v_in=v_in)
        current = interval_current(m._charge(s["v_in"], dt), dt)
        return -m.feedback_resistance * (current + m.bias_current)
