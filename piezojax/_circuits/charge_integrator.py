"""Paper 001 (Ivan et al. 2009): the piezo charge read by an integrator with a reference capacitor."""

import jax
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    check_component,
    check_positive_param,
    check_scalar_param,
    error_if_not_finite,
    error_if_not_positive,
)
from .._creep.base import AbstractCreep
from .._custom_types import Signal, SignalLike
from .._dtypes import param_dtype
from .._hysteresis.base import AbstractHysteresis, change_from_rest
from .._linear.base import AbstractLinearSystem
from .base import (
    AbstractCircuit,
    prepare,
    running_integral,
)


def integrator_constants(integrator_capacitance, reference_capacitance, leakage_resistance, bias_current,
                         force_sensitivity, dtype) -> tuple[Array, ...]:
    """Paper 001's charge-integrator constants $C$, $C_R$, $R_{FP}$, the bias current and $\beta$, checked (positive;
    the bias current finite) in `dtype`: the circuit and its observer (`pj.ForceDisplacementObserver`) share them."""
    return (check_positive_param(integrator_capacitance, "integrator_capacitance", dtype=dtype),
            check_positive_param(reference_capacitance, "reference_capacitance", dtype=dtype),
            check_positive_param(leakage_resistance, "leakage_resistance", dtype=dtype),
            check_scalar_param(bias_current, "bias_current", dtype=dtype),
            check_positive_param(force_sensitivity, "force_sensitivity", dtype=dtype))


class ChargeIntegratorCircuit(AbstractCircuit):
    r"""Charge integrator with reference capacitor, leakage and bias current (paper 001, eq. 1, 3, 4).

    Piezo charge (eq. 1 with the nonlinear parts of eq. 4):
    $Q_P = \beta F_{ext} + \mathcal{H}[V_{in}] + \mathcal{F}_C[V_{in}]$, where $\mathcal{H}$ is the hysteretic
    charge–voltage operator (its linear part is the capacitance $C_P V_{in}$; a Prandtl–Ishlinskii operator in the
    paper) and $\mathcal{F}_C$ the creep charge (a transfer function, eq. 9). With `hysteresis=None` the charge is
    the linear $C_P V_{in}$ of eq. 1 (`capacitance_p`). The integrator is reset at rest: it collects the change
    of $Q_P$ from the demagnetised operator's charge at $V_{in} = 0$ (0 for an operator that `rests_at_zero`).

    Integrator output. Solving eq. (3) for $V_{out}$ with $F_{est} = F_{ext}$ gives our reading of the circuit: the
    integrator capacitor $C$ collects the piezo charge, the charge $-C_R V_{in}$ of the reference capacitor driven in
    anti-phase, the leakage current $V_{in}/R_{FP}$ of the piezo and the op-amp bias current:

    $V_{out} = -\frac{1}{C}\left(Q_P - C_R V_{in} + \int_0^t \left(\frac{V_{in}}{R_{FP}} + i_{bias}\right)dt\right)$.

    Integrals follow the rectangle convention of `piezojax._circuits.base` (exactly inverted by
    `ForceDisplacementObserver`). Sign conventions: $\beta > 0$ with $F_{ext} > 0$ the force that opposes the motion
    driven by negative $V_{in}$ (it reduces $|Q_P|$).

    **Arguments:**

    - `integrator_capacitance`: $C > 0$ [F].
    - `reference_capacitance`: $C_R > 0$ [F].
    - `leakage_resistance`: $R_{FP} > 0$ [Ω].
    - `bias_current`: $i_{bias}$ [A] (constant; default 0).
    - `force_sensitivity`: $\beta > 0$ [C/N] (1.03 nC/mN in the paper).
    - `capacitance_p`: $C_P \ge 0$ [F] (1.74 nF in the paper), used when `hysteresis` is `None`.
    - `hysteresis`: the charge–voltage operator $\mathcal{H}$ [C] (a `pj.AbstractHysteresis`, called as `op(v_in)`,
      e.g. `pj.PrandtlIshlinskii` with weights in F), or `None`.
    - `creep`: $\mathcal{F}_C$ [C/V], a `pj.AbstractCreep` or `pj.AbstractLinearSystem` called as `creep(v_in, dt)`
      (e.g. a `pj.TransferFunction`), or `None`.

    ```python
    circuit = pj.ChargeIntegratorCircuit(100e-9, 1.74e-9, 1e12, 0.0, 1.03e-6, capacitance_p=1.74e-9)
    v_out = circuit(v_in, 1e-3, f_ext)   # integrator output [V]
    ```
    """

    integrator_capacitance: Float[Array, ""]
    reference_capacitance: Float[Array, ""]
    leakage_resistance: Float[Array, ""]
    bias_current: Float[Array, ""]
    force_sensitivity: Float[Array, ""]
    capacitance_p: Float[Array, ""]
    hysteresis: AbstractHysteresis | None
    creep: AbstractCreep | AbstractLinearSystem | None

    def __init__(
        self,
        integrator_capacitance: ArrayLike,
        reference_capacitance: ArrayLike,
        leakage_resistance: ArrayLike,
        bias_current: ArrayLike,
        force_sensitivity: ArrayLike,
        capacitance_p: ArrayLike = 0.0,
        hysteresis: AbstractHysteresis | None = None,
        creep: AbstractCreep | AbstractLinearSystem | None = None,
    ):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((integrator_capacitance, reference_capacitance, leakage_resistance,
                                              bias_current, force_sensitivity, capacitance_p, hysteresis, creep)))
        (self.integrator_capacitance, self.reference_capacitance, self.leakage_resistance, self.bias_current,
         self.force_sensitivity) = integrator_constants(integrator_capacitance, reference_capacitance,
                                                        leakage_resistance, bias_current, force_sensitivity, dtype)
        self.capacitance_p = check_positive_param(capacitance_p, "capacitance_p", allow_zero=True, dtype=dtype)
        self.hysteresis = check_component(hysteresis, AbstractHysteresis, "hysteresis", "op(v)")
        self.creep = check_component(creep, (AbstractCreep, AbstractLinearSystem), "creep", "creep(v, dt)")

    def check(self) -> "ChargeIntegratorCircuit":
        names = ("integrator_capacitance", "reference_capacitance", "leakage_resistance", "force_sensitivity",
                 "capacitance_p")
        m = error_if_not_positive(self, names, allow_zero=("capacitance_p",))
        return error_if_not_finite(m, ("bias_current",))

    def _voltage_charge(self, v_in: Array, dt: Array) -> Array:
        # reset at rest, the integrator collects the change from the demagnetised operator's charge at 0 V
        q = self.capacitance_p * v_in if self.hysteresis is None else change_from_rest(self.hysteresis, v_in)
        if self.creep is not None:
            q = q + self.creep(v_in, dt)
        return q

    def _charge(self, v_in: Array, dt: Array, f_ext: Array | None) -> Array:
        q = self._voltage_charge(v_in, dt)
        if f_ext is not None:
            q = q + self.force_sensitivity * f_ext
        return q

    def charge(self, v_in: SignalLike, dt: ArrayLike, f_ext: SignalLike | None = None) -> Signal:
        r"""The piezo charge $Q_P = \beta F_{ext} + \mathcal{H}[V_{in}] + \mathcal{F}_C[V_{in}]$ [C]."""
        m, dt, s = prepare(self, dt, v_in=v_in, f_ext=f_ext)
        return m._charge(s["v_in"], dt, s["f_ext"])

    def __call__(self, v_in: SignalLike, dt: ArrayLike, f_ext: SignalLike | None = None) -> Signal:
        r"""The integrator output $V_{out}$ [V] for the drive `v_in` [V] and contact force `f_ext` [N] (default 0).

        **Arguments:**

        - `v_in`: drive voltage samples, shape `(time,)`.
        - `dt`: sample step [s].
        - `f_ext`: external force on the tip, same length as `v_in`, or `None` (free actuator): the circuit's
          `load` (`AbstractCircuit.__call__`).

        **Returns:** $V_{out}$, shape `(time,)`.
        """
        m, dt, s = prepare(self, dt, v_in=v_in, f_ext=f_ext)
        v = s["v_in"]
        q = m._charge(v, dt, s["f_ext"])
        leak = running_integral(v, dt, 1 / m.leakage_resistance, m.bias_current)
        return -(q - m.reference_capacitance * v + leak) / m.integrator_capacitance
