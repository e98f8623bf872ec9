"""Virtual bench of paper 000: a PIC151/Ni unimorph driven by voltage steps, read by a transimpedance amplifier."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from .._circuits.base import interval_current
from .._creep.lags import lag_sum
from .._linear.base import AbstractLinearSystem
from .._linear.transfer_function import TransferFunction
from .._observers.dynamic_impedance import DynamicImpedanceObserver
from .common import AbstractSelfSensingBench, Record, bench_param, bench_signal, lag, measure, replace_fields


def unimorph_dynamics(static_gain: float = 1e-7, corner_hz: float = 30.0, resonance_hz: float = 380.0,
                      damping: float = 0.02) -> TransferFunction:
    r"""3rd-order $G(s) = g\,\omega_1\omega_n^2 / ((s + \omega_1)(s^2 + 2\zeta\omega_n s + \omega_n^2))$ of the bench.

    Defaults: $g$ = 0.1 µm per unit of $F_t$ (8.97 µm free deflection at 100 V with the paper's α); a first
    bending resonance at 380 Hz, our Euler–Bernoulli estimate for a 20 × 2 × 0.27 mm PZT/Ni cantilever; a 30 Hz
    real pole for the slow part of the transient the paper's ARMAX model captures.
    """
    w1, wn = 2 * np.pi * corner_hz, 2 * np.pi * resonance_hz
    return TransferFunction([static_gain * w1 * wn**2], np.polymul([1.0, w1], [1.0, 2 * damping * wn, wn**2]))


class BafumbaBench(AbstractSelfSensingBench):
    r"""Virtual bench of paper 000 (Bafumba Liseli et al. 2018), richer than its observer.

    Truth, per sample ($dt = 1/f_s$):

    - high-voltage amplifier: $V = \frac{1}{1 + \tau_{hv}s} V_{cmd}$;
    - charge: $Q = C_r V - \gamma\tanh(|V|/V_\gamma)\,V + Q_c$ (the capacitance drop sets in over a few volts instead
      of the observer's constant $\gamma$), creep charge $Q_c = \sum_i \frac{q_i}{1 + \tau_i s}
      \left[V (1 + |V|/V_E)\right]$ (two time constants, field-dependent: the observer never models it, it measures it);
    - transimpedance amplifier with bandwidth: $V_{out} = -R_f \frac{1}{1 + \tau_f s}\left(I + I_{bias}(t)\right)$,
      $I_{bias}(t) = I_{bias} + \dot I_{bias} t$ (op-amp bias drift, not known to the observer);
    - displacement: $\delta = G(s)\left[\alpha V + \beta Q_c\right]$, with the paper's α, β (eq. 9–13).

    Recorded channels: `v_in` from a 1/20 monitor output, `v_out`, `displacement` from an optical sensor, each with
    white noise and a 16-bit ±10 V converter (`adc_bits=0` disables quantisation).

    Ground truth from the paper: γ = 0.66 nF (Table I), α = 0.8971, β = 6.9067e7 (eq. 12–13). Our plausible
    choices: $C_r$ = 4.2 nF (PIC 151, ε_r ≈ 2400, 20 × 2 mm electrode, 0.2 mm thick), $V_\gamma$ = 2 V, creep
    0.25 + 0.35 nC/V with τ = 20 s and 250 s and $V_E$ = 400 V (≈ 6 % creep at 100 V), $R_f$ = 470 kΩ (OPA111),
    $I_{bias}$ = 1 pA drifting 0.5 pA per 1000 s, $\tau_{hv}$ = 50 ms (keeps 200 V steps inside ±10 V),
    $\tau_f$ = 0.2 ms, 1 kHz sampling, noise 0.3 mV on $V_{out}$, 5 mV on $V_{in}$, 10 nm on the displacement.

    **Arguments:** every field below can be overridden by keyword.

    ```python
    bench = pj.BafumbaBench()
    rec = bench.record(pj.step_command([100.0], hold=1000.0, sample_rate=1e3, rest=2.0), jax.random.key(0))
    est = bench.observer()(rec.v_in, rec.v_out, rec.dt)     # δ̂ with the bench's true parameters
    ```
    """

    capacitance: Array
    gamma: Array
    gamma_onset: Array
    creep_charges: Array
    creep_times: Array
    creep_field: Array
    feedback_resistance: Array
    bias_current: Array
    bias_drift: Array
    tia_time_constant: Array
    hv_time_constant: Array
    alpha: Array
    beta: Array
    dynamics: AbstractLinearSystem
    v_out_noise: float = eqx.field(static=True)
    v_in_noise: float = eqx.field(static=True)
    displacement_noise: float = eqx.field(static=True)
    adc_bits: int = eqx.field(static=True)
    sample_rate: float = eqx.field(static=True)

    def __init__(
        self,
        *,
        capacitance: ArrayLike = 4.2e-9,
        gamma: ArrayLike = 0.66e-9,
        gamma_onset: ArrayLike = 2.0,
        creep_charges: ArrayLike = (0.25e-9, 0.35e-9),
        creep_times: ArrayLike = (20.0, 250.0),
        creep_field: ArrayLike = 400.0,
        feedback_resistance: ArrayLike = 470e3,
        bias_current: ArrayLike = 1e-12,
        bias_drift: ArrayLike = 0.5e-15,
        tia_time_constant: ArrayLike = 2e-4,
        hv_time_constant: ArrayLike = 0.05,
        alpha: ArrayLike = 0.8971,
        beta: ArrayLike = 6.9067e7,
        dynamics: AbstractLinearSystem | None = None,
        v_out_noise: float = 0.3e-3,
        v_in_noise: float = 5e-3,
        displacement_noise: float = 10e-9,
        adc_bits: int = 16,
        sample_rate: float = 1e3,
    ):
        self.capacitance = bench_param(capacitance, "capacitance")
        self.gamma = bench_param(gamma, "gamma")
        self.gamma_onset = bench_param(gamma_onset, "gamma_onset")
        self.creep_charges = bench_param(creep_charges, "creep_charges")
        self.creep_times = bench_param(creep_times, "creep_times")
        self.creep_field = bench_param(creep_field, "creep_field")
        self.feedback_resistance = bench_param(feedback_resistance, "feedback_resistance")
        self.bias_current = bench_param(bias_current, "bias_current")
        self.bias_drift = bench_param(bias_drift, "bias_drift")
        self.tia_time_constant = bench_param(tia_time_constant, "tia_time_constant")
        self.hv_time_constant = bench_param(hv_time_constant, "hv_time_constant")
        self.alpha = bench_param(alpha, "alpha")
        self.beta = bench_param(beta, "beta")
        self.dynamics = unimorph_dynamics() if dynamics is None else dynamics
        self.v_out_noise, self.v_in_noise, self.displacement_noise = v_out_noise, v_in_noise, displacement_noise
        self.adc_bits, self.sample_rate = adc_bits, sample_rate

    def ideal(self) -> "BafumbaBench":
        """The same bench without noise, quantisation or bias drift (deterministic channels)."""
        b = eqx.tree_at(lambda b: b.bias_drift, self, self.bias_drift * 0)
        return replace_fields(b, adc_bits=0, v_out_noise=0.0, v_in_noise=0.0, displacement_noise=0.0)

    def observer(self) -> DynamicImpedanceObserver:
        """The paper-000 observer with the bench's true (nominal) parameters: $R_f$, $C_r$, γ, $I_{bias}$, α, β, G."""
        return DynamicImpedanceObserver(self.feedback_resistance, self.capacitance, self.gamma, self.bias_current,
                                        self.alpha, self.beta, self.dynamics)

    def creep_charge(self, v: Array, dt: Array) -> Array:
        u = v * (1 + jnp.abs(v) / self.creep_field)
        return lag_sum(self.creep_charges, self.creep_times, u, dt, "interval")

    def record(self, v_command: ArrayLike, key: PRNGKeyArray) -> Record:
        """Simulate one record for the commanded voltage samples `v_command` [V] (from rest), seeded by `key`.

        Works under `eqx.filter_jit` and `jax.vmap` (over commands and keys). Gradients with respect to the
        bench's parameters exist for the `true_*` channels; the quantised channels have zero gradient.

        **Returns:** a `Record` with `t`, `v_in`, `v_out`, `displacement` (and `force=None`) plus the truth.
        """
        dtype = self.capacitance.dtype
        v_cmd = bench_signal(v_command, "v_command", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        t = jnp.arange(v_cmd.shape[0], dtype=dtype) * dt
        v = lag(v_cmd, dt, self.hv_time_constant)
        q_c = self.creep_charge(v, dt)
        q = self.capacitance * v - self.gamma * jnp.tanh(jnp.abs(v) / self.gamma_onset) * v + q_c
        current = interval_current(q, dt) + self.bias_current + self.bias_drift * t
        v_out = -self.feedback_resistance * lag(current, dt, self.tia_time_constant)
        delta = self.dynamics.simulate(self.alpha * v + self.beta * q_c, dt)
        k1, k2, k3 = jax.random.split(key, 3)
        bits = self.adc_bits
        quant = (lambda x, k, s, g: measure(x, k, s, bits, 10.0, g)) if bits else (
            lambda x, k, s, g: x + s * jax.random.normal(k, x.shape, x.dtype))
        return Record(
            t=t,
            v_in=quant(v, k1, self.v_in_noise, 1 / 20),
            v_out=quant(v_out, k2, self.v_out_noise, 1.0),
            displacement=quant(delta, k3, self.displacement_noise, 2e5),
            force=None,
            true_v_in=v,
            true_displacement=delta,
            true_force=None,
        )
