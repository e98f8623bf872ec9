"""Virtual bench of paper 002: a smart piezo stack (sensor layer + charge amplifier) in a preloaded flexure stage."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import PiezojaxValueError
from .._circuits.smart_stack import SmartStackCircuit
from .._control.base import AbstractPlant
from .._creep.lags import zoh_lag_coefficients
from .._dtypes import matmul
from .._hysteresis.bouc_wen import BoucWen
from .._linear.transfer_function import TransferFunction
from .._observers.sensor_layer import SensorLayerObserver
from .common import AbstractSelfSensingBench, Record, adc, bench_param, bench_signal, lag, measure, replace_fields


class ChenBench(AbstractSelfSensingBench):
    r"""Virtual bench of paper 002 (Chen & Li 2014), richer than the eq. (9) observer.

    Truth: a rate-dependent stack displacement $x_a = s_x\,(h + \kappa\,\mathcal{L}_{\tau_c}[h])$ with
    $h = \mathcal{B}[\mathcal{L}_{\tau_e}[V_a]]$: a Bouc–Wen hysteresis $\mathcal{B}$ (the paper only says $f$ is
    hysteretic, eq. 2) driven through the electrical lag $\tau_e$ of amplifier and stack capacitance, plus a creep
    of fraction $\kappa$ (first-order lag $\mathcal{L}_{\tau_c}$) — so the loop widens and tilts with the frequency,
    the rate dependence the paper reports (Section III-A; the fitted models here are rate-independent operators or
    networks, not this). Sensor force from the stage dynamics eq. (3) (`SmartStackCircuit`); sensor voltage
    through a real charge amplifier, which cannot hold DC (time constant $\tau_{ca}$, the reason the paper
    calibrates from 1 Hz up): $V_s = \frac{\tau_{ca}s}{1 + \tau_{ca}s}\left[\frac{d_{33}}{C}F_s\right] + p_c V_a$.

    Ground truth from the paper: $d_{33}/C$ = 0.015381 V/N (force sensitivity), $C$ = 104 pF, displacement
    sensitivity $(k_p + k_s)C/(k_p k_s d_{33})$ = 11.6126 µm/V, which with our $k_s$ = 50 N/µm fixes
    $k_p$ = 6.30 N/µm. Crosstalk $p_c = -0.006636/20$ V/V (the paper's FEA value for 20 V). Plausible choices:
    stage $m_e$ = 50 g, $k_e$ = 20 N/µm, ζ = 0.05 (3.2 kHz), Bouc–Wen A = 0.15, β = 0.01, γ = 0.005 /V
    (≈ 10 % hysteresis over 0–100 V), $s_x$ = 0.1 µm/V (6 µm peak to peak, the paper's triangles,
    take 60 V), $\tau_e$ = 0.2 ms, $\kappa$ = 3 %, $\tau_c$ = 50 ms, $\tau_{ca}$ = 100 s, 10 kHz sampling,
    noise 0.5 mV on $V_s$, 5 nm on the laser displacement, 0.05 N on the reference force, 16-bit ±10 V
    converters.

    ```python
    bench = pj.ChenBench()
    rec = bench.record(50 + 50 * jnp.sin(2 * jnp.pi * 5 * jnp.arange(20000) / 1e4), jax.random.key(0))
    est = bench.observer()(rec.v_in, rec.v_out)
    ```
    """

    stack: SmartStackCircuit
    hysteresis: BoucWen
    stroke: Array
    electrical_time_constant: Array
    creep_fraction: Array
    creep_time_constant: Array
    amplifier_time_constant: Array
    v_s_noise: float = eqx.field(static=True)
    displacement_noise: float = eqx.field(static=True)
    force_noise: float = eqx.field(static=True)
    adc_bits: int = eqx.field(static=True)
    sample_rate: float = eqx.field(static=True)

    def __init__(
        self,
        *,
        force_sensitivity: float = 0.015381,
        displacement_sensitivity: float = 11.6126e-6,
        amplifier_capacitance: float = 104e-12,
        k_s: float = 5e7,
        m_e: float = 0.05,
        k_e: float = 2e7,
        damping_ratio: float = 0.05,
        crosstalk: float = -0.006636 / 20,
        hysteresis: BoucWen | None = None,
        stroke: ArrayLike = 1e-7,
        electrical_time_constant: ArrayLike = 2e-4,
        creep_fraction: ArrayLike = 0.03,
        creep_time_constant: ArrayLike = 0.05,
        amplifier_time_constant: ArrayLike = 100.0,
        v_s_noise: float = 0.5e-3,
        displacement_noise: float = 5e-9,
        force_noise: float = 0.05,
        adc_bits: int = 16,
        sample_rate: float = 1e4,
    ):
        k_p = 1 / (displacement_sensitivity * force_sensitivity - 1 / k_s)
        c_e = 2 * damping_ratio * (k_e * m_e) ** 0.5
        d33 = force_sensitivity * amplifier_capacitance
        self.stack = SmartStackCircuit(d33, amplifier_capacitance, k_p, k_s, m_e, c_e, k_e, crosstalk=crosstalk)
        self.hysteresis = BoucWen(0.15, 0.01, 0.005, d=1.0) if hysteresis is None else hysteresis
        self.stroke = bench_param(stroke, "stroke")
        self.electrical_time_constant = bench_param(electrical_time_constant, "electrical_time_constant")
        self.creep_fraction = bench_param(creep_fraction, "creep_fraction")
        self.creep_time_constant = bench_param(creep_time_constant, "creep_time_constant")
        self.amplifier_time_constant = bench_param(amplifier_time_constant, "amplifier_time_constant")
        self.v_s_noise, self.displacement_noise, self.force_noise = v_s_noise, displacement_noise, force_noise
        self.adc_bits, self.sample_rate = adc_bits, sample_rate

    def ideal(self) -> "ChenBench":
        """The same bench without noise or quantisation."""
        return replace_fields(self, adc_bits=0, v_s_noise=0.0, displacement_noise=0.0, force_noise=0.0)

    def observer(self, crosstalk: bool = True) -> SensorLayerObserver:
        """The eq. (9) observer with the bench's true parameters (with the crosstalk term unless `crosstalk=False`)."""
        s = self.stack
        obs = SensorLayerObserver(s.d33, s.amplifier_capacitance, s.k_p, s.k_s, crosstalk=s.crosstalk)
        return obs if crosstalk else obs.without_crosstalk()

    def displacement_truth(self, v_a: ArrayLike) -> Float[Array, " time"]:
        r"""The true stack displacement $x_a$ [m] for the drive samples `v_a` [V] at `sample_rate`, from rest."""
        dtype = self.stroke.dtype
        v = bench_signal(v_a, "v_a", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        h = self.hysteresis(lag(v, dt, self.electrical_time_constant))
        return self.stroke * (h + self.creep_fraction * lag(h, dt, self.creep_time_constant))

    def _acquire(self, key: PRNGKeyArray, v: Array, v_s: Array, x: Array, force: Array) -> Record:
        dtype = v.dtype
        t = jnp.arange(v.shape[0], dtype=dtype) / jnp.asarray(self.sample_rate, dtype)
        k1, k2, k3 = jax.random.split(key, 3)
        bits = self.adc_bits
        quant = (lambda x, k, s, g: measure(x, k, s, bits, 10.0, g)) if bits else (
            lambda x, k, s, g: x + s * jax.random.normal(k, x.shape, x.dtype))
        return Record(
            t=t,
            v_in=v if not bits else measure(v, k1, 0.0, bits, 10.0, 1 / 20),
            v_out=quant(v_s, k1, self.v_s_noise, 1.0),
            displacement=quant(x, k2, self.displacement_noise, 1e5),
            force=quant(force, k3, self.force_noise, 0.05),
            true_v_in=v,
            true_displacement=x,
            true_force=force,
        )

    def _charge_amplifier(self, force: Array, dt: Array) -> Array:
        charge_signal = self.stack.d33 / self.stack.amplifier_capacitance * force
        return charge_signal - lag(charge_signal, dt, self.amplifier_time_constant)

    def record(self, v_a: ArrayLike, key: PRNGKeyArray) -> Record:
        """Simulate one record for the actuator drive samples `v_a` [V] (from rest), seeded by `key`.

        Works under `eqx.filter_jit` and `jax.vmap` (over commands and keys). Gradients with respect to the
        bench's parameters exist for the `true_*` channels; the quantised channels have zero gradient.

        **Returns:** a `Record`: `v_in` = $V_a$, `v_out` = $V_s$, `displacement` = $x_a$, `force` = $F_s$.
        """
        dtype = self.stroke.dtype
        v = bench_signal(v_a, "v_a", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        x_a = self.displacement_truth(v)
        force = self.stack.sensor_force(x_a, dt)
        v_s = self._charge_amplifier(force, dt) + self.stack.crosstalk * v
        return self._acquire(key, v, v_s, x_a, force)

    def record_isolated(self, v_a: ArrayLike, key: PRNGKeyArray) -> Record:
        """The stack out of the stage (no preload, free to expand): the sensor reads only the crosstalk
        $p_c V_a$ (paper 002 Fig. 13). Same channels as `record`; `force` is 0."""
        dtype = self.stroke.dtype
        v = bench_signal(v_a, "v_a", dtype)
        x_a = self.displacement_truth(v)
        return self._acquire(key, v, self.stack.crosstalk * v, x_a, jnp.zeros_like(v))

    def record_force_calibration(self, force: ArrayLike, key: PRNGKeyArray) -> Record:
        """Paper 002's sensor calibration (Fig. 6–8): the stage on a stiff support, the actuator shorted, an exciter
        pushing with `force` [N] through a reference force sensor. `force` is that sensor's channel, `v_out` the
        charge amplifier's; `v_in` and `displacement` are 0."""
        dtype = self.stroke.dtype
        f = bench_signal(force, "force", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        zero = jnp.zeros_like(f)
        return self._acquire(key, zero, self._charge_amplifier(f, dt), zero, f)

    def plant(
        self,
        dt: float = 1e-3,
        *,
        substeps: int = 10,
        amplifier_gain: float = 20.0,
        dac_bits: int = 16,
        dac_range: float = 10.0,
        v_min: float = -20.0,
        v_max: float = 200.0,
        bias: float = 0.0,
        settle: float = 0.5,
    ) -> "ChenStagePlant":
        """This bench as a sampled plant for `pj.closed_loop` (paper 002's control rig, Section V-A).

        **Arguments:**

        - `dt`: the control period [s] (1 kHz in the paper).
        - `substeps`: integration steps per period (the drive is held, the truth is integrated on the finer grid).
        - `amplifier_gain` [V/V], `dac_bits`, `dac_range` [V]: the command $u$ (the stack voltage wanted) is written
          by a `dac_bits`-bit converter of range ±`dac_range` V (NI PXI-6733: 16 bits, ±10 V) and amplified
          `amplifier_gain` times (20 V/V), then limited to [`v_min`, `v_max`] (−20 V to 200 V); `dac_bits=0`: no
          quantisation.
        - `bias` [V]: the voltage the stage rests at before the first command (paper: 100 V, so that it can move
          both ways), reached by a ramp from 0 V and held `settle` seconds; the charge amplifier is reset there
          and the `displacement` and `laser` channels read from that rest position (as the laser is zeroed).

        **Returns:** a `ChenStagePlant`; its noise samples are `jax.random.normal(key, (time, 2))` (sensor voltage,
        laser displacement), scaled by the bench's noise levels.
        """
        return ChenStagePlant(self, dt, substeps, amplifier_gain, dac_bits, dac_range, v_min, v_max, bias, settle)


class ChenStagePlant(AbstractPlant):
    r"""`ChenBench`'s truth as a sampled plant (`pj.AbstractPlant`), built by `ChenBench.plant`.

    Each period the command is quantised by the DAC, amplified and limited, then held; the truth (electrical lag,
    Bouc–Wen, creep, stage dynamics eq. 3 discretised exactly for a drive held on each sub-step, charge amplifier)
    advances `substeps` times. `output(state, noise)` gives the channels `v_in` (the stack voltage), `v_out` (the
    sensor voltage with noise and the bench's ADC), `displacement` (the true $x_a$), `laser` (the laser sensor's
    reading) and `force` (the true $F_s$).
    """

    bench: ChenBench
    coefficients: tuple[tuple[Array, Array], ...]
    stage: tuple[Array, Array, Array, Array]
    rest: tuple[Array, ...]
    dt: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    amplifier_gain: float = eqx.field(static=True)
    dac_bits: int = eqx.field(static=True)
    dac_range: float = eqx.field(static=True)
    v_min: float = eqx.field(static=True)
    v_max: float = eqx.field(static=True)

    def __init__(self, bench, dt, substeps, amplifier_gain, dac_bits, dac_range, v_min, v_max, bias=0.0, settle=0.5):
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise PiezojaxValueError(f"`substeps` must be a positive int, got {substeps!r}")
        if isinstance(dac_bits, bool) or not isinstance(dac_bits, int) or dac_bits < 0:
            raise PiezojaxValueError(f"`dac_bits` must be an int >= 0 (0: no quantisation), got {dac_bits!r}")
        for name, value in (("dt", dt), ("amplifier_gain", amplifier_gain), ("dac_range", dac_range)):
            if not math.isfinite(value) or not value > 0:
                raise PiezojaxValueError(f"`{name}` must be finite and > 0, got {value!r}")
        for name, value in (("bias", bias), ("settle", settle)):
            if not math.isfinite(value):
                raise PiezojaxValueError(f"`{name}` must be finite, got {value!r}")
        if not v_max > v_min:  # NaN fails too
            raise PiezojaxValueError(f"`v_max` must be greater than `v_min`, got {v_min!r}, {v_max!r}")
        self.bench, self.dt, self.substeps = bench, float(dt), substeps
        self.amplifier_gain, self.dac_bits, self.dac_range = float(amplifier_gain), int(dac_bits), float(dac_range)
        self.v_min, self.v_max = float(v_min), float(v_max)
        dtype = bench.stroke.dtype
        h = jnp.asarray(self.dt / substeps, dtype)
        self.coefficients = tuple(  # (a, 1 - a) of each ZOH lag over a substep
            zoh_lag_coefficients(tau, h) for tau in (bench.electrical_time_constant, bench.creep_time_constant,
                                                     bench.amplifier_time_constant)
        )
        s = bench.stack
        zero = jnp.zeros((), dtype)
        high_pass = TransferFunction(jnp.stack([s.m_e, zero, zero]), jnp.stack([s.m_e, s.c_e, s.k_e]))
        d = high_pass.discretise(h, "zoh")
        self.stage = (d.Ad, d.Bd, d.Cd, d.Dd)
        z = jnp.zeros((), dtype)
        state = (z, z, bench.hysteresis.init(), z, jnp.zeros(d.Ad.shape[0], dtype), z, z, z, z)
        if not (bias == 0 or settle >= 0):
            raise PiezojaxValueError(f"`settle` must be >= 0, got {settle!r}")
        if bias != 0:
            n_ramp, n_hold = max(int(round(0.1 / self.dt)), 1), int(round(settle / self.dt))
            ramp = jnp.linspace(0, bias, n_ramp + 1, dtype=dtype)[1:]
            drive = jnp.concatenate([ramp, jnp.full(n_hold, bias, dtype)])
            self.rest = state  # step() reads only the static fields and the coefficients set above
            state = jax.lax.scan(lambda st, u: (self._advance(st, u), None), state, drive)[0]
            # the charge amplifier is reset at rest: its output restarts from the crosstalk alone
            reading = bench.stack.crosstalk * state[0]
            state = (*state[:5], state[5] + state[7] - reading, state[6], reading, state[8])
        self.rest = state

    def init(self):
        """At rest at `bias` (0 V by default): `(v_a, v_p, bouc-wen state, creep, stage state, amplifier lag, x_a,
        v_s, F_s)`."""
        return self.rest

    def drive(self, command: Array) -> Array:
        """The stack voltage for a command: DAC quantisation and range, amplifier gain, output limits."""
        g = self.amplifier_gain
        code = jnp.clip(command / g, -self.dac_range, self.dac_range)
        if self.dac_bits:
            code = _straight_through(code, adc(code, self.dac_bits, self.dac_range))
        return jnp.clip(g * code, self.v_min, self.v_max)

    def step(self, state, command):
        return self._advance(state, command)

    def _advance(self, state, command):
        b, s = self.bench, self.bench.stack
        (a_e, b_e), (a_c, b_c), (a_a, b_a) = self.coefficients
        Ad, Bd, Cd, Dd = self.stage
        v_a = self.drive(jnp.asarray(command, b.stroke.dtype))
        k_ser = s.series_stiffness()
        gain = s.d33 / s.amplifier_capacitance

        def sub(carry, _):
            v_p, bw, creep, xi, amp, _, _, _ = carry
            v_p = a_e * v_p + b_e * v_a
            bw, h = b.hysteresis.step(bw, v_p)
            creep = a_c * creep + b_c * h
            x = b.stroke * (h + b.creep_fraction * creep)
            force = k_ser * x + s.k_e * (matmul(Cd, xi) + Dd * x)
            xi = matmul(Ad, xi) + Bd * x
            signal = gain * force
            amp = a_a * amp + b_a * signal
            return (v_p, bw, creep, xi, amp, x, signal - amp + s.crosstalk * v_a, force), None

        carry, _ = jax.lax.scan(sub, state[1:], None, length=self.substeps)
        return (v_a, *carry)

    def output(self, state, noise):
        b = self.bench
        v_a, x, v_s, force = state[0], state[6] - self.rest[6], state[7], state[8]
        n = jnp.zeros((2,), v_s.dtype) if noise is None else noise
        v_out = v_s + b.v_s_noise * n[0]
        laser = x + b.displacement_noise * n[1]
        if b.adc_bits:
            v_out = _straight_through(v_out, adc(v_out, b.adc_bits, 10.0))
        return {"v_in": v_a, "v_out": v_out, "displacement": x, "laser": laser, "force": force}


def _straight_through(x: Array, quantised: Array) -> Array:
    """`quantised` in value, `x` in derivative: a converter's rounding has a zero derivative almost everywhere,
    which would hide every gradient through a loop; its slope on average is 1."""
    return x + jax.lax.stop_gradient(quantised - x)
