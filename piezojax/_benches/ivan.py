"""Virtual bench of paper 001: a PZT/Ni cantilever pushing on a force sensor, read by a charge integrator."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from .._checks import PiezojaxValueError, check_finite, check_positive
from .._circuits.base import apply_operator, running_integral
from .._hysteresis.base import AbstractHysteresis
from .._hysteresis.play import (
    _AbstractStopCell,
    param_dtype,
    stop_update,
)
from .._observers.current_integration import ForceDisplacementObserver
from .common import Record, bench_param, bench_signal, lag, measure, replace_fields


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


class GaussianPreisach(_AbstractStopCell):
    r"""A Preisach operator with a separable Gaussian density, computed exactly in $s$ through its play form.

    With half-width $r = (\alpha - \beta)/2$ and centre $s = (\alpha + \beta)/2$, the relay of the demagnetised
    Preisach operator is $R_{\alpha,\beta}[v] = \mathrm{sign}(P_r[v] - s)$, $P_r$ the play operator started at 0
    (Mayergoyz; Krejčí). For a density $\mu(r, s)$ (per unit $r$ and $s$) that is even in $s$,

    $$\int_0^\infty\!\!\int_{-\infty}^{\infty}\mu\,\mathrm{sign}(P_r[v] - s)\,ds\,dr
      = 2\int_0^\infty\!\!\int_0^{P_r[v]}\mu(r, s)\,ds\,dr,$$

    and for $\mu = c\,e^{-r^2/2\sigma_r^2}e^{-s^2/2\sigma_s^2}$ the inner integral is an error function of the
    play output. With the midpoint rule on $n$ nodes $r_j = (j + \tfrac12)h$, $h = r_{\max}/n$:

    $$y = w_0 v + \sum_j w_j\,\varphi(P_{r_j}[v]),\quad \varphi(p) = \int_0^p e^{-s^2/2\sigma_s^2}ds
      = \sigma_s\sqrt{\pi/2}\,\mathrm{erf}\bigl(p/(\sqrt2\sigma_s)\bigr),\quad
      w_j = 2c\,h\,e^{-r_j^2/2\sigma_r^2}.$$

    A "generalised Prandtl–Ishlinskii" operator with odd, saturating shape $\varphi$ (the PI class has $\varphi(p) =
    p$, reached as $\sigma_s \to \infty$): it is a Preisach operator (density on the lines $r = r_j$, Gaussian in
    $s$), so it has return-point memory, wiping-out and congruent minor loops, which Bouc–Wen lacks. Plays with $r \geq
    \max|v|$ never leave 0, so truncating the $r$ integral at $r_{\max}$ is exact for inputs within $\pm r_{\max}$;
    the midpoint rule in $r$ is the only discretisation (for the `IvanBench` default, $h$ = 1 V, it is within
    8e-3 V of $h$ = 1/8 V on the paper's contact drive, against a 1.6 V loop width). Exact plays by default;
    `smoothing` $> 0$ uses the smooth rate-independent play of `play_step`. Works under `jit`, `vmap`, `jax.grad`
    and `jax.jacfwd`.

    **Arguments:**

    - `density`: $c$ [1/V], the density at the origin (per V of $r$ and per V of $s$).
    - `sigma_r`, `sigma_s` [V]: widths of the density in half-width and centre.
    - `w0`: the reversible linear gain.
    - `r_max` [V], `n`: quadrature range and number of nodes (static).
    - `smoothing`: relative play smoothing $\geq 0$ (0 = exact); static (a Python float, no gradient).

    **Returns:** called on a signal of shape `(time,)`, the output, shape `(time,)` (in the units of the input).

    ```python
    op = GaussianPreisach(0.005, 100.0, 100.0, w0=0.9)
    y = op(-20.0 * jnp.abs(jnp.sin(jnp.linspace(0, 6, 3000))))
    ```
    """

    w0: Array
    weights: Array
    thresholds: Array
    sigma_s: Array
    smoothing: float = eqx.field(static=True)
    _block: int = eqx.field(static=True, default=1024)

    def __init__(self, density: ArrayLike, sigma_r: ArrayLike, sigma_s: ArrayLike, *, w0: ArrayLike = 1.0,
                 r_max: float = 100.0, n: int = 100, smoothing: float = 0.0):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PiezojaxValueError(f"`n` must be a positive int, got {n!r}")
        if not (np.isfinite(r_max) and r_max > 0):
            raise PiezojaxValueError(f"`r_max` must be finite and > 0, got {r_max!r}")
        dtype = param_dtype(density, sigma_r, sigma_s, w0)
        density, sigma_r = jnp.asarray(density, dtype), jnp.asarray(sigma_r, dtype)
        for name, x in (("density", density), ("sigma_r", sigma_r), ("sigma_s", sigma_s), ("w0", w0)):
            if jnp.ndim(x) != 0:
                raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {jnp.shape(x)}")
        density = check_positive(density, "density", allow_zero=True)
        sigma_r = check_positive(sigma_r, "sigma_r")
        h = float(r_max) / n
        r = jnp.asarray((np.arange(n) + 0.5) * h, dtype)
        self.thresholds = r
        self.weights = 2 * density * h * jnp.exp(-0.5 * (r / sigma_r) ** 2)
        self.sigma_s = jnp.asarray(sigma_s, dtype)
        self.sigma_s = check_positive(self.sigma_s, "sigma_s", allow_zero=True)
        self.w0 = check_finite(jnp.asarray(w0, dtype), "w0")
        # Static: a bench's truth keeps one form, and a traced smoothing would compile both loops (`lax.cond`).
        if not (isinstance(smoothing, (int, float, np.floating)) and np.isfinite(smoothing) and smoothing >= 0):
            raise PiezojaxValueError(f"`smoothing` must be a finite Python float >= 0 (0 = exact), got {smoothing!r}")
        self.smoothing = float(smoothing)

    def check(self) -> "GaussianPreisach":
        sig = check_positive(self.sigma_s, "sigma_s")
        return eqx.tree_at(lambda o: (o.sigma_s, o.weights, o.thresholds), self,
                           (sig, check_positive(self.weights, "weights", allow_zero=True),
                            check_positive(self.thresholds, "thresholds", allow_zero=True)))

    def _output(self, v: Array, z: Array) -> Array:
        sig = self.sigma_s
        c = jnp.sqrt(jnp.asarray(0.5, v.dtype))
        phi = sig * jnp.sqrt(jnp.pi / 2).astype(v.dtype) * jax.lax.erf(c * (v[..., None] - z) / sig)
        return self.w0 * v + phi @ self.weights

    def _run(self, state, signal):
        # The plays run in a tight loop over blocks of samples and the shape function is applied to each block at
        # once: an erf per play per sample inside the loop is 2-3x slower (measured: 1e6 samples, 100 plays).
        # Padding repeats the last sample, which moves no play, so the final state is unchanged.
        t = signal.shape[0]
        b = min(t, self._block)
        pad = (-t) % b
        blocks = jnp.concatenate([signal, jnp.broadcast_to(signal[-1], (pad,))]).reshape(-1, b)

        def run(exact):
            def inner(carry, v):
                v_prev, z = carry
                z = stop_update(z, v - v_prev, self.thresholds, self.smoothing, exact)
                return (v, z), z

            def outer(carry, vb):
                carry, zb = jax.lax.scan(inner, carry, vb)
                return carry, self._output(vb, zb)

            return jax.lax.scan(outer, state, blocks)

        final, y = run(self.smoothing == 0)
        return final, y.reshape(-1)[:t]


class LagCreep(eqx.Module):
    r"""Creep as a sum of first-order lags, $\sum_i \frac{g_i}{1 + \tau_i s}$, exact for held samples, from rest.

    Called as `creep(u, dt)`, like the creep blocks; used by the benches and as their true creep operator.
    """

    gains: Array
    times: Array

    def __call__(self, u: Array, dt: ArrayLike) -> Array:
        u = jnp.asarray(u)
        dt = jnp.asarray(dt, u.dtype)
        return self.gains.astype(u.dtype) @ jax.vmap(lambda tau: lag(u, dt, tau))(self.times.astype(u.dtype))


class ScaledOperator(eqx.Module):
    """`gain * op(v)` for a signal-to-signal operator `op` (e.g. a hysteresis cell in volts turned into charge)."""

    gain: Array
    op: eqx.Module

    def __call__(self, v: Array) -> Array:
        # A hysteresis cell runs through its own `_run` (GaussianPreisach's blocked loop is 2-3x faster than a scan
        # of `step`).
        y = self.op(v) if isinstance(self.op, AbstractHysteresis) else apply_operator(self.op, v)
        return self.gain.astype(v.dtype) * y


class IvanBench(eqx.Module):
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

    A 1000 s record (1e6 samples) takes 4.6 s under `eqx.filter_jit` after compilation (30 s for the first call) on
    the 2-core development CPU while it ran other jobs (load average 11).
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

    def true_charge_operators(self) -> tuple[ScaledOperator, LagCreep]:
        """The bench's own charge operators `(hysteresis, creep)` in the observer's form: with them the observer's
        model is exact (only noise, quantisation and bias drift remain)."""
        return (ScaledOperator(self.capacitance_p, self.hysteresis),
                LagCreep(self.capacitance_p * self.creep_fractions, self.creep_times))

    def free_charge(self, v: Array, dt: Array) -> Array:
        """$Q_V$ [C]: hysteretic charge plus creep charge of the free actuator."""
        hysteresis, creep = self.true_charge_operators()
        return hysteresis(v) + creep(v, dt)

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
