"""Virtual bench of paper 001: a PZT/Ni cantilever pushing on a force sensor, read by a charge integrator."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from .._circuits.base import running_integral
from .._creep.kelvin_voigt import KelvinVoigtCreep
from .._creep.lags import lag_sum
from .._hysteresis.base import AbstractHysteresis
from .._hysteresis.preisach import GaussianPreisach
from .._hysteresis.scaled import ScaledHysteresis
from .._observers.current_integration import ForceDisplacementObserver
from .common import AbstractSelfSensingBench, Record, bench_param, bench_signal, measure, replace_fields


def periodic_steps(levels=(-10.0, -20.0), period: float = 4.0, slope: float = 100.0, cycles: int = 3,
                   sample_rate: float = 1e3) -> np.ndarray:
    """Paper 001's contact experiment drive: ramped steps from 0 V to each of `levels` and back, repeated.

    Each half period holds the level, the other half 0 V; edges are ramps of `slope` [V/s].

    **Returns:** a NumPy array of drive samples.

    ```python
    v = pj.periodic_steps((-10.0, -20.0), period=4.0, cycles=3)
    ```
    """
    n = int(round(period * sample_rate))
    t = np.arange(n) / sample_rate
    out = []
    for _ in range(cycles):
        for level in levels:
            up = np.minimum(t * slope, abs(level))
            down = np.clip(abs(level) - (t - period / 2) * slope, 0, abs(level))
            out.append(np.sign(level) * np.where(t < period / 2, up, down))
    return np.concatenate(out)


class IvanBench(AbstractSelfSensingBench):
    r"""Virtual bench of paper 001 (Ivan et al. 2009): gap, then contact with a force sensor of finite stiffness.

    Truth:

    - charge of the free actuator $Q_V = C_P\,\mathcal{G}[V] + Q_c$ with a Preisach hysteresis $\mathcal{G}$
      (`GaussianPreisach`; the observer assumes Prandtl–Ishlinskii) and a two-time-constant creep
      $Q_c = C_P\sum_i \frac{c_i}{1 + \tau_i s}V$ (the observer assumes one LTI transfer function);
    - free deflection proportional to that charge (ref. 1 of the paper): $\delta_{free} = Q_V/\alpha$, $\alpha < 0$
      so that negative voltages move the tip towards the sensor ($\delta > 0$);
    - a force sensor of stiffness $k_{fs}$ at gap $g$: $F = \frac{k_{fs}k}{k_{fs} + k}\max(0, \delta_{free} - g)$,
      tip position $\delta = \delta_{free} - F/k$ with the beam stiffness $k$;
    - piezo charge $Q_P = \beta F + Q_V$, read by `ChargeIntegratorCircuit`'s law with a drifting bias current.

    Ground truth from the paper: $C_P$ = 1.74 nC/V, β = 1.03 nC/mN, blocking force 0.07 mN/V, which with our
    beam stiffness $k$ = 163 N/m (3EI/L³ for 15 × 1 × 0.28 mm PZT/Ni) gives 0.43 µm/V of free deflection, hence
    α = −C_P / 0.43 µm/V = −4.06e-3 C/m.

    Hysteresis: $\mathcal{G}[V] = w_0 V + \sum_j w_j\varphi(P_{r_j}[V])$, a Preisach operator with density
    $c\,e^{-r^2/2\sigma_r^2}e^{-s^2/2\sigma_s^2}$ (see `GaussianPreisach`), $\sigma_r = \sigma_s$ = 100 V,
    $c$ = 0.0161 /V², $w_0$ = 0.84, 100 nodes on $r \le$ 100 V. Why: a Preisach operator has return-point memory and
    congruent minor loops, as piezoceramics approximately do (Bouc–Wen has neither and ratchets under the paper's
    one-sided steps, which no PI follows). The drive, 20 V p-p, is 10 % of the actuator's range (the paper) and a
    small fraction of the PZT's coercive field; there the converse effect follows the Rayleigh law (Damjanovic 1996),
    which is a Preisach operator with a density nearly constant near the origin (Néel; Robert, Damjanovic & Setter
    2001). So the density's width is put at the drive range, σ = 100 V (within 2 % of its peak over 0..−20 V, only
    weakly non-PI: $\varphi$ bends by 0.7 % at 20 V). The scale $c$ gives a cycled 0 ↔ −20 V loop of maximum width
    8 % of its span (the previous Bouc–Wen bench's stated figure; in the Rayleigh limit width = $c E_0^2$ at amplitude
    $E_0$ = 10 V, i.e. $c$ = 0.016) and $w_0$ makes that loop's chord slope 1, so $C_P$ is the chord capacitance of
    the cycle (in Rayleigh terms the irreversible part is 16 % of the 10 V-amplitude response). The first excursion
    from the demagnetised state runs on the initial curve, 16 % steeper, so $g$ = 2.5 µm (adjusted "close to
    contact" as in the paper) gives ≈ 1.14 mN peak at −20 V, as the paper's 1.15 mN.

    Other plausible choices: creep 2 % and 3 % of $C_P$ with τ = 10 s and 100 s, $k_{fs}$ = 2000 N/m,
    $C$ = 10 nF, $C_R$ = 1.5 nF, $R_{FP}$ = 100 GΩ, $i_{bias}$ = 10 fA drifting 1 fA per 100 s, 1 kHz sampling, noise
    0.2 mV on $V_{out}$, 2 µN on the force sensor, 20 nm on the optical displacement sensor, 16-bit ±10 V converters.
    Pass `hysteresis=` for another operator in volts (e.g. `BoucWen(0.1, 0.01, 0.01, d=1.0)`, the previous truth).
    """

    capacitance_p: Array
    hysteresis: AbstractHysteresis
    creep_fractions: Array
    creep_times: Array
    alpha: Array
    force_sensitivity: Array
    beam_stiffness: Array
    sensor_stiffness: Array
    gap: Array
    integrator_capacitance: Array
    reference_capacitance: Array
    leakage_resistance: Array
    bias_current: Array
    bias_drift: Array
    v_out_noise: float = eqx.field(static=True)
    force_noise: float = eqx.field(static=True)
    displacement_noise: float = eqx.field(static=True)
    adc_bits: int = eqx.field(static=True)
    sample_rate: float = eqx.field(static=True)

    def __init__(
        self,
        *,
        capacitance_p: ArrayLike = 1.74e-9,
        hysteresis: AbstractHysteresis | None = None,
        creep_fractions: ArrayLike = (0.02, 0.03),
        creep_times: ArrayLike = (10.0, 100.0),
        blocking_force: float = 0.07e-3,
        force_sensitivity: ArrayLike = 1.03e-6,
        beam_stiffness: float = 163.0,
        sensor_stiffness: ArrayLike = 2000.0,
        gap: ArrayLike = 2.5e-6,
        integrator_capacitance: ArrayLike = 10e-9,
        reference_capacitance: ArrayLike = 1.5e-9,
        leakage_resistance: ArrayLike = 1e11,
        bias_current: ArrayLike = 10e-15,
        bias_drift: ArrayLike = 1e-17,
        v_out_noise: float = 0.2e-3,
        force_noise: float = 2e-6,
        displacement_noise: float = 20e-9,
        adc_bits: int = 16,
        sample_rate: float = 1e3,
    ):
        self.capacitance_p = bench_param(capacitance_p, "capacitance_p")
        self.hysteresis = (GaussianPreisach(0.0161, 100.0, 100.0, w0=0.84, r_max=100.0, n=100)
                           if hysteresis is None else hysteresis)
        self.creep_fractions = bench_param(creep_fractions, "creep_fractions")
        self.creep_times = bench_param(creep_times, "creep_times")
        self.force_sensitivity = bench_param(force_sensitivity, "force_sensitivity")
        self.beam_stiffness = bench_param(beam_stiffness, "beam_stiffness")
        self.sensor_stiffness = bench_param(sensor_stiffness, "sensor_stiffness")
        self.gap = bench_param(gap, "gap")
        self.integrator_capacitance = bench_param(integrator_capacitance, "integrator_capacitance")
        self.reference_capacitance = bench_param(reference_capacitance, "reference_capacitance")
        self.leakage_resistance = bench_param(leakage_resistance, "leakage_resistance")
        self.bias_current = bench_param(bias_current, "bias_current")
        self.bias_drift = bench_param(bias_drift, "bias_drift")
        self.alpha = bench_param(-capacitance_p / (blocking_force / beam_stiffness), "blocking_force")
        self.v_out_noise, self.force_noise, self.displacement_noise = v_out_noise, force_noise, displacement_noise
        self.adc_bits, self.sample_rate = adc_bits, sample_rate

    def ideal(self) -> "IvanBench":
        """The same bench without noise, quantisation or bias drift."""
        b = eqx.tree_at(lambda b: b.bias_drift, self, self.bias_drift * 0)
        return replace_fields(b, adc_bits=0, v_out_noise=0.0, force_noise=0.0, displacement_noise=0.0)

    def identified_stiffness(self) -> Array:
        r"""$k_Z$ as the paper identifies it (force step at $V_{in} = 0$): $1/k_Z = 1/k + \beta/\alpha$."""
        return 1 / (1 / self.beam_stiffness + self.force_sensitivity / self.alpha)

    def observer(self, hysteresis=None, creep=None, filter_cutoff=None) -> ForceDisplacementObserver:
        """The paper-001 observer with the bench's circuit constants, α, β and $k_Z$; `hysteresis`/`creep` are the
        identified charge operators (default: the linear $C_P$ and no creep)."""
        return ForceDisplacementObserver(
            self.integrator_capacitance, self.reference_capacitance, self.leakage_resistance, self.bias_current,
            self.force_sensitivity, self.alpha, self.identified_stiffness(), capacitance_p=self.capacitance_p,
            hysteresis=hysteresis, creep=creep, filter_cutoff=filter_cutoff)

    def true_charge_operators(self) -> tuple[ScaledHysteresis, KelvinVoigtCreep]:
        """The bench's own charge operators `(hysteresis, creep)` in the observer's form: with them the observer's
        model is exact (only noise, quantisation and bias drift remain). The creep is the Kelvin–Voigt chain without
        instantaneous term, $1/k_i = C_P c_i$ (held drive samples, as the observer reads them), so it needs every
        creep fraction > 0; `free_charge` computes the same creep without that restriction."""
        return (ScaledHysteresis(self.hysteresis, self.capacitance_p),
                KelvinVoigtCreep(1 / (self.capacitance_p * self.creep_fractions), self.creep_times, k0=None))

    def free_charge(self, v: Array, dt: Array) -> Array:
        """$Q_V$ [C]: hysteretic charge plus creep charge of the free actuator."""
        creep = lag_sum(self.capacitance_p * self.creep_fractions, self.creep_times, v, dt, "zoh")
        return self.capacitance_p * self.hysteresis(v) + creep

    def record(self, v_in: ArrayLike, key: PRNGKeyArray) -> Record:
        """Simulate one record for the drive samples `v_in` [V] (from rest), seeded by `key`.

        Works under `eqx.filter_jit` and `jax.vmap` (over commands and keys). Gradients with respect to the
        bench's parameters exist for the `true_*` channels; the quantised channels have zero gradient.

        **Returns:** a `Record` with `v_in`, `v_out` (integrator), `displacement` and `force` (reference sensors).
        """
        dtype = self.capacitance_p.dtype
        v = bench_signal(v_in, "v_in", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        t = jnp.arange(v.shape[0], dtype=dtype) * dt
        q_v = self.free_charge(v, dt)
        d_free = q_v / self.alpha
        k, ks = self.beam_stiffness, self.sensor_stiffness
        force = ks * k / (ks + k) * jnp.maximum(d_free - self.gap, 0)
        delta = d_free - force / k
        q = self.force_sensitivity * force + q_v
        i_bias = self.bias_current + self.bias_drift * t
        leak = running_integral(v / self.leakage_resistance + i_bias, dt)
        v_out = -(q - self.reference_capacitance * v + leak) / self.integrator_capacitance
        k1, k2, k3 = jax.random.split(key, 3)
        bits = self.adc_bits
        quant = (lambda x, kk, s, g: measure(x, kk, s, bits, 10.0, g)) if bits else (
            lambda x, kk, s, g: x + s * jax.random.normal(kk, x.shape, x.dtype))
        return Record(
            t=t,
            v_in=v if not bits else measure(v, k1, 0.0, bits, 10.0, 1 / 5),
            v_out=quant(v_out, k1, self.v_out_noise, 1.0),
            displacement=quant(delta, k2, self.displacement_noise, 5e5),
            force=quant(force, k3, self.force_noise, 5e3),
            true_v_in=v,
            true_displacement=delta,
            true_force=force,
        )
