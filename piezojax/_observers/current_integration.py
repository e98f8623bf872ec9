"""Paper 001 (Ivan et al. 2009): force and displacement self-sensing by current integration."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    check_component,
    check_nonzero,
    check_positive_param,
    check_scalar_param,
    error_if_not_finite,
    error_if_not_positive,
)
from .._circuits.base import (
    prepare,
    running_integral,
)
from .._circuits.charge_integrator import integrator_constants
from .._creep.base import AbstractCreep
from .._custom_types import Signal, SignalLike
from .._dtypes import param_dtype
from .._hysteresis.base import AbstractHysteresis, change_from_rest
from .._linear.base import AbstractLinearSystem
from .._linear.butterworth import butterworth_zoh
from .base import AbstractObserver, Estimate


class ForceDisplacementObserver(AbstractObserver):
    r"""Force and displacement observer of paper 001 (eq. 4–6), the inverse of `ChargeIntegratorCircuit`.

    The compensated charge (bias, leakage and reference-capacitor terms removed) is
    $Q = -C V_{out} + C_R V_{in} - \int_0^t \left(\frac{V_{in}}{R_{FP}} + i_{bias}\right)dt$, and

    - force (eq. 4): $F_{est} = \frac{1}{\beta}\left(Q - \mathcal{F}_H[V_{in}] - \mathcal{F}_C[V_{in}]\right)$,
      with the hysteresis operator $\mathcal{F}_H$ (PI, eq. 7–8) and creep $\mathcal{F}_C$ (eq. 9) in charge units
      (the paper identifies them on $V^*_{out} = -Q/C$, i.e. with weights scaled by $-1/C$);
    - free displacement (eq. 5): $\delta_{free} = Q/\alpha$;
    - displacement (eq. 6): $\hat\delta = \delta_{free} - B(s)[F_{est}]/k_Z$, $B$ the 3rd-order Butterworth
      low-pass the paper puts on the force term (`filter_cutoff=None` for none).

    $k_Z$ is the stiffness identified the paper's way (an external force step at $V_{in} = 0$); for a beam of
    stiffness $k$ this is $1/k_Z = 1/k + \beta/\alpha$, which makes eq. (6) exact (see `IvanBench`).

    **Arguments:**

    - `integrator_capacitance` $C$, `reference_capacitance` $C_R$ [F] > 0; `leakage_resistance` $R_{FP}$ [Ω] > 0;
      `bias_current` $i_{bias}$ [A].
    - `force_sensitivity` $\beta$ [C/N] > 0; `displacement_coefficient` $\alpha$ [C/m] (≠ 0, signed);
      `stiffness` $k_Z$ [N/m] > 0.
    - `capacitance_p` [F]: the linear $C_P$ used when `hysteresis` is `None` (then eq. 4 reduces to eq. 3).
    - `hysteresis`: $\mathcal{F}_H$ (a `pj.AbstractHysteresis` in C, called as `op(v_in)`), or `None`.
    - `creep`: $\mathcal{F}_C$ (a `pj.AbstractCreep` or `pj.AbstractLinearSystem`, called as `creep(v_in, dt)`), or
      `None`.
    - `filter_cutoff`: Butterworth cutoff [Hz], or `None`.
    - `offset` [m]: added to the displacement estimate (the zero of the displacement sensor it is compared with).
    - `prehistory` $u_p$ [V], or `None`: the remanent state of $\mathcal{F}_H$ from the actuator's last use, as an
      excursion $0 \to u_p \to 0$ of the demagnetised operator before the record (as `pj.Actuator`'s). The
      integrator is reset at $t = 0$, so it reads charge *changes*: the operator's charge enters as
      $\mathcal{F}_H[V](t) - h_r$, $h_r$ its remanent output at the end of the excursion. Needs `hysteresis`.

    ```python
    obs = pj.ForceDisplacementObserver(100e-9, 1.74e-9, 1e12, 0.0, 1.03e-6, -4e-3, 150.0,
                                       hysteresis=pi_charge, filter_cutoff=10.0)
    est = obs(v_in, v_out, 1e-3)         # est.force [N], est.displacement [m]
    ```
    """

    estimates: ClassVar[tuple[str, ...]] = ("displacement", "force")

    integrator_capacitance: Float[Array, ""]
    reference_capacitance: Float[Array, ""]
    leakage_resistance: Float[Array, ""]
    bias_current: Float[Array, ""]
    force_sensitivity: Float[Array, ""]
    displacement_coefficient: Float[Array, ""]
    stiffness: Float[Array, ""]
    capacitance_p: Float[Array, ""]
    hysteresis: AbstractHysteresis | None
    creep: AbstractCreep | AbstractLinearSystem | None
    filter_cutoff: Float[Array, ""] | None
    offset: Float[Array, ""]
    prehistory: Float[Array, ""] | None

    def __init__(
        self,
        integrator_capacitance: ArrayLike,
        reference_capacitance: ArrayLike,
        leakage_resistance: ArrayLike,
        bias_current: ArrayLike,
        force_sensitivity: ArrayLike,
        displacement_coefficient: ArrayLike,
        stiffness: ArrayLike,
        capacitance_p: ArrayLike = 0.0,
        hysteresis: AbstractHysteresis | None = None,
        creep: AbstractCreep | AbstractLinearSystem | None = None,
        filter_cutoff: ArrayLike | None = None,
        *,
        offset: ArrayLike = 0.0,
        prehistory: ArrayLike | None = None,
    ):
        # Python numbers (defaults included) follow the arrays' dtype
        dtype = param_dtype(*jax.tree.leaves((integrator_capacitance, reference_capacitance, leakage_resistance,
                                              bias_current, force_sensitivity, displacement_coefficient, stiffness,
                                              capacitance_p, hysteresis, creep, filter_cutoff, offset, prehistory)))
        (self.integrator_capacitance, self.reference_capacitance, self.leakage_resistance, self.bias_current,
         self.force_sensitivity) = integrator_constants(integrator_capacitance, reference_capacitance,
                                                        leakage_resistance, bias_current, force_sensitivity, dtype)
        self.displacement_coefficient = check_nonzero(
            check_scalar_param(displacement_coefficient, "displacement_coefficient", dtype=dtype),
            "displacement_coefficient",
        )
        self.stiffness = check_positive_param(stiffness, "stiffness", dtype=dtype)
        self.capacitance_p = check_positive_param(capacitance_p, "capacitance_p", allow_zero=True, dtype=dtype)
        self.hysteresis = check_component(hysteresis, AbstractHysteresis, "hysteresis", "op(v)")
        self.creep = check_component(creep, (AbstractCreep, AbstractLinearSystem), "creep", "creep(v, dt)")
        self.filter_cutoff = None if filter_cutoff is None else check_positive_param(filter_cutoff, "filter_cutoff",
                                                                                     dtype=dtype)
        self.offset = check_scalar_param(offset, "offset", dtype=dtype)
        if prehistory is not None and hysteresis is None:
            raise PiezojaxValueError("`prehistory` sets the remanent state of `hysteresis`; the observer has none")
        self.prehistory = None if prehistory is None else check_scalar_param(prehistory, "prehistory", dtype=dtype)

    def check(self) -> "ForceDisplacementObserver":
        names = ("integrator_capacitance", "reference_capacitance", "leakage_resistance", "force_sensitivity",
                 "stiffness", "capacitance_p") + (("filter_cutoff",) if self.filter_cutoff is not None else ())
        m = error_if_not_positive(self, names, allow_zero=("capacitance_p",))
        m = error_if_not_finite(m, ("bias_current", "offset") + (("prehistory",) if m.prehistory is not None else ()))
        alpha = check_nonzero(m.displacement_coefficient, "displacement_coefficient")
        return eqx.tree_at(lambda o: o.displacement_coefficient, m, alpha)

    def _compensated_charge(self, v: Array, v_out: Array, dt: Array) -> Array:
        leak = running_integral(v, dt, 1 / self.leakage_resistance, self.bias_current)
        return -self.integrator_capacitance * v_out + self.reference_capacitance * v - leak

    def compensated_charge(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike) -> Signal:
        """The piezo charge recovered from the integrator output, with bias, leakage and $C_R$ terms removed [C]."""
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        return m._compensated_charge(s["v_in"], s["v_out"], dt)

    def __call__(self, v_in: SignalLike, v_out: SignalLike, dt: ArrayLike) -> Estimate:
        r"""Force (eq. 4) and displacement (eq. 6) estimates.

        **Arguments:**

        - `v_in`: drive voltage [V], shape `(time,)`; `v_out`: integrator output [V], same length.
        - `dt`: sample step [s].

        **Returns:** an `Estimate` with `force` $F_{est}$ [N] and `displacement` $\hat\delta$ [m].
        """
        m, dt, s = prepare(self, dt, v_in=v_in, v_out=v_out)
        v = s["v_in"]
        q = m._compensated_charge(v, s["v_out"], dt)
        if m.hysteresis is None:
            q_v = m.capacitance_p * v
        else:  # the integrator reads the change from rest: after the excursion 0 -> u_p -> 0, or demagnetised
            path = None if m.prehistory is None else jnp.stack([m.prehistory.astype(v.dtype), jnp.zeros((), v.dtype)])
            q_v = change_from_rest(m.hysteresis, v, path)
        if m.creep is not None:
            q_v = q_v + m.creep(v, dt)
        force = (q - q_v) / m.force_sensitivity
        if m.filter_cutoff is None:
            force_term = force
        else:  # = pj.butterworth(3, 2 pi f_c).simulate(force, dt), in its modal form (faster under jacfwd)
            force_term = butterworth_zoh(3, 2 * jnp.pi * m.filter_cutoff, force, dt)
        displacement = q / m.displacement_coefficient - force_term / m.stiffness + m.offset
        return Estimate(displacement=displacement, force=force)
