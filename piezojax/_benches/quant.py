"""Virtual bench of paper 003: a MIDE QP20W piezoceramic wafer driven by a high-voltage amplifier, with a strain
gauge and a charge amplifier (the thesis' characterisation set-up, Ch. 4)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from .._checks import PiezojaxValueError, check_value
from .._creep.lags import lag_sum
from .._dtypes import matmul
from .._hysteresis.preisach import Preisach
from .._linear.base import StateSpace
from .common import AbstractBench, Record, bench_param, bench_signal, lag, measure, replace_fields


def charge_preisach(total_charge: float = 8.0e-6, levels: int = 40, v_max: float = 300.0,
                    centre: float = 0.0, spread: float = 150.0, bias: float = 20.0, bias_spread: float = 100.0
                    ) -> Preisach:
    r"""The bench's polarisation-charge hysteresis: a smooth `Preisach` operator on a uniform grid of `levels`
    levels over $\pm$`v_max` [V] whose density is a Gaussian in the relay half-width $r = (\alpha - \beta)/2$
    (centre `centre`, width `spread`) times one in its midpoint $m = (\alpha + \beta)/2$ (centre `bias`, width
    `bias_spread`: an off-centre density gives the asymmetric, non-congruent loops a Maxwell-slip model cannot
    reproduce), scaled so that the weights sum to `total_charge` [C]; smoothing half a grid step. The defaults
    make a Rayleigh-like law (the small-signal capacitance grows with the amplitude up to 200 V) with loops
    11 % of the charge range wide at ±150 V and 3 % at ±30 V."""
    op = Preisach.uniform(-v_max, v_max, levels)
    r = 0.5 * (op.alpha - op.beta)
    m = 0.5 * (op.alpha + op.beta)
    w = jnp.exp(-0.5 * ((r - centre) / spread) ** 2 - 0.5 * ((m - bias) / bias_spread) ** 2)
    mu = total_charge * w / jnp.sum(w)
    return Preisach(op.alpha, op.beta, mu, 0.0, v_max / levels)


_POSITIVE = ("capacitance", "coupling_voltage", "creep_time", "stiffness", "hv_time_constant", "feedback_capacitance",
             "frequencies", "participations")
_NONNEGATIVE = ("creep_fraction", "dampings", "load_stiffness", "load_mass", "load_damping")
_MODES = ("frequencies", "dampings", "participations")


def _checked_fields(bench: "QuantBench", fields: tuple[str, ...], names: dict[str, str] | None = None) -> tuple:
    """The bench's numbers `fields` with their value checks (`check_value`: a `PiezojaxValueError` naming the
    argument for concrete values, a runtime check when traced): scalars where one is expected (a shape, checked
    now), signs, and participations summing to 1. `names` maps fields to the names the caller used."""
    names = names or {}
    out = []
    for field in fields:
        value, name = getattr(bench, field), names.get(field, field)
        if field not in _MODES and jnp.ndim(value) != 0:
            raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {jnp.shape(value)}")
        if field in _POSITIVE:
            value = check_value(value, lambda x: x > 0, f"`{name}` must be > 0")
        elif field in _NONNEGATIVE:
            value = check_value(value, lambda x: x >= 0, f"`{name}` must be >= 0")
        if field == "participations":
            value = check_value(value, lambda p: jnp.abs(jnp.sum(p) - 1) <= 1e-9,
                                "`participations` must sum to 1 (x = F/k at rest)")
        out.append(value)
    return tuple(out)


_CHECKED = _POSITIVE + _NONNEGATIVE + ("coupling", "coupling_variation")
_LOAD = ("load_stiffness", "load_mass", "load_damping")


class QuantBench(AbstractBench):
    r"""Virtual bench of paper 003 (Quant 2009 thesis, Ch. 4): a MIDE QP20W wafer, richer than the thesis' model.

    The thesis' model (`ElectromechanicalActuator`) puts a Maxwell-slip hysteresis voltage in series with the
    piezo's capacitance. The bench's truth is built differently, per sample ($dt = 1/f_s$):

    - high-voltage amplifier: $V = \frac{1}{1 + \tau_{hv} s} V_{cmd}$;
    - polarisation charge with Preisach hysteresis (`charge_preisach`: a 2-D density, so minor loops are not
      congruent, which no Maxwell-slip or Prandtl–Ishlinskii model reproduces): $Q_V = C_0 V + \mathcal{P}[V]$;
    - transducer force with a voltage-dependent coupling (the thesis' $d_{31}(V)$, its Fig. 33) and a creep:
      $F = \frac{T_0}{C_0}\left(1 + a\tanh(V/V_a)\right) Q_V$, then $F_c = F + c\,\frac{1}{1 + \tau_c s}F$;
    - mechanics: two modes at the wafer's elongation $x$ (mode $i$: stiffness $k/p_i$, frequency $f_i$, damping
      ratio $\zeta_i$, so that $x = F_c/k$ at rest with $\sum p_i = 1$), and an optional load at $x$ (the thesis'
      cantilever, Ch. 6: stiffness $K_L$, mass $m_L$, damping $c_L$), integrated exactly (`StateSpace`, first-order
      hold of the force);
    - charge: $q = Q_V + T_0 x$ (the direct effect).

    Recorded channels: `v_in` from the amplifier's 1/200 monitor, `displacement` $= x = \varepsilon L$ from a
    strain-gauge bridge (average strain ε times the active length $L$), and `v_out` $= -q/C_f$ from a charge
    amplifier with feedback capacitor $C_f$ (`charge(v_out)` converts back), each with white noise and a 16-bit
    ±10 V converter. `truth(command)` gives every noise-free signal, the charge included.

    Our plausible choices (the thesis' Table 3 and Table 5 are not in our copy of the text): $C_0$ = 90 nF;
    $L$ = 46 mm; $k$ = 4.1 MN/m and $T_0$ = 0.21 N/V (with the hysteresis, about 240 µε at +150 V and −190 µε at
    −150 V; a coupling factor $T_0^2/(kC_0) \approx 0.12$); modes at 300 and 850 Hz ($\zeta$ 0.03, 0.02, the second
    carrying 6 %); $a$ = 0.12, $V_a$ = 150 V (d31 9 % higher at +150 V than at 0, 9 % lower at −150 V); creep 2 % with $\tau_c$ = 1.5 s; $\tau_{hv}$ = 20 µs;
    2 kHz sampling; noise 20 mV on $V$, 0.3 µε on the strain, 1 nC on the charge; $C_f$ = 4 µF.

    **Arguments:** every field below can be overridden by keyword.

    ```python
    bench = pj.QuantBench()
    rec = bench.record(150 * np.sin(2 * np.pi * np.arange(4000) / 2000), jax.random.key(0))
    strain, charge = rec.displacement / bench.length, bench.charge(rec.v_out)
    ```
    """

    capacitance: Array
    hysteresis: Preisach
    coupling: Array
    coupling_variation: Array
    coupling_voltage: Array
    creep_fraction: Array
    creep_time: Array
    stiffness: Array
    frequencies: Array
    dampings: Array
    participations: Array
    load_stiffness: Array
    load_mass: Array
    load_damping: Array
    hv_time_constant: Array
    feedback_capacitance: Array
    length: float = eqx.field(static=True)
    v_in_noise: float = eqx.field(static=True)
    strain_noise: float = eqx.field(static=True)
    charge_noise: float = eqx.field(static=True)
    adc_bits: int = eqx.field(static=True)
    sample_rate: float = eqx.field(static=True)

    def __init__(
        self,
        *,
        capacitance: ArrayLike = 90e-9,
        hysteresis: Preisach | None = None,
        coupling: ArrayLike = 0.21,
        coupling_variation: ArrayLike = 0.12,
        coupling_voltage: ArrayLike = 150.0,
        creep_fraction: ArrayLike = 0.02,
        creep_time: ArrayLike = 1.5,
        stiffness: ArrayLike = 4.1e6,
        frequencies: ArrayLike = (300.0, 850.0),
        dampings: ArrayLike = (0.03, 0.02),
        participations: ArrayLike = (0.94, 0.06),
        load_stiffness: ArrayLike = 0.0,
        load_mass: ArrayLike = 0.0,
        load_damping: ArrayLike = 0.0,
        hv_time_constant: ArrayLike = 2e-5,
        feedback_capacitance: ArrayLike = 4e-6,
        length: float = 0.046,
        v_in_noise: float = 20e-3,
        strain_noise: float = 0.3e-6,
        charge_noise: float = 1e-9,
        adc_bits: int = 16,
        sample_rate: float = 2e3,
    ):
        self.capacitance = bench_param(capacitance, "capacitance")
        self.hysteresis = charge_preisach() if hysteresis is None else hysteresis
        if not isinstance(self.hysteresis, Preisach):
            raise PiezojaxValueError(f"`hysteresis` must be a pj.Preisach, got {type(hysteresis).__name__}")
        self.coupling = bench_param(coupling, "coupling")
        self.coupling_variation = bench_param(coupling_variation, "coupling_variation")
        self.coupling_voltage = bench_param(coupling_voltage, "coupling_voltage")
        self.creep_fraction = bench_param(creep_fraction, "creep_fraction")
        self.creep_time = bench_param(creep_time, "creep_time")
        self.stiffness = bench_param(stiffness, "stiffness")
        self.frequencies = bench_param(frequencies, "frequencies")
        self.dampings = bench_param(dampings, "dampings")
        self.participations = bench_param(participations, "participations")
        shapes = {self.frequencies.shape, self.dampings.shape, self.participations.shape}
        if len(shapes) != 1 or self.frequencies.ndim != 1 or self.frequencies.size == 0:
            raise PiezojaxValueError("`frequencies`, `dampings` and `participations` must be 1-D of one length "
                                     f"(one entry per mode), got shapes {sorted(shapes)}")
        self.load_stiffness = bench_param(load_stiffness, "load_stiffness")
        self.load_mass = bench_param(load_mass, "load_mass")
        self.load_damping = bench_param(load_damping, "load_damping")
        self.hv_time_constant = bench_param(hv_time_constant, "hv_time_constant")
        self.feedback_capacitance = bench_param(feedback_capacitance, "feedback_capacitance")
        self.length = float(length)
        for field, value in zip(_CHECKED, _checked_fields(self, _CHECKED)):
            setattr(self, field, value)
        self.v_in_noise, self.strain_noise, self.charge_noise = v_in_noise, strain_noise, charge_noise
        self.adc_bits, self.sample_rate = adc_bits, sample_rate

    def ideal(self) -> "QuantBench":
        """The same bench without noise or quantisation (deterministic channels)."""
        return replace_fields(self, adc_bits=0, v_in_noise=0.0, strain_noise=0.0, charge_noise=0.0)

    def with_load(self, stiffness: ArrayLike, mass: ArrayLike = 0.0, damping: ArrayLike = 0.0) -> "QuantBench":
        """The bench with a load at the wafer's elongation: a spring `stiffness` [N/m], a mass `mass` [kg] and a
        damper `damping` [N s/m] (the thesis' cantilever beam as an equivalent stiffness and mass, Ch. 6)."""
        loaded = eqx.tree_at(lambda b: (b.load_stiffness, b.load_mass, b.load_damping), self,
                             (bench_param(stiffness, "stiffness"), bench_param(mass, "mass"),
                              bench_param(damping, "damping")))
        names = {"load_stiffness": "stiffness", "load_mass": "mass", "load_damping": "damping"}
        return eqx.tree_at(lambda b: tuple(getattr(b, f) for f in _LOAD), loaded, _checked_fields(loaded, _LOAD, names))

    def mechanics(self) -> StateSpace:
        r"""The modes with the load, from the transducer force to $x$: $M\ddot\eta + C\dot\eta + K\eta = F\mathbf 1$,
        $x = \mathbf 1^\top\eta$, with $K = \mathrm{diag}(k/p_i) + K_L\mathbf 1\mathbf 1^\top$,
        $M = \mathrm{diag}(k/(p_i\omega_i^2)) + m_L\mathbf 1\mathbf 1^\top$ and $C$ alike."""
        w = 2 * jnp.pi * self.frequencies
        k_i = self.stiffness / self.participations
        m_i = k_i / w**2
        c_i = 2 * self.dampings * w * m_i
        n = w.shape[0]
        ones = jnp.ones((n, n), w.dtype)
        mass = jnp.diag(m_i) + self.load_mass * ones
        stiff = jnp.diag(k_i) + self.load_stiffness * ones
        damp = jnp.diag(c_i) + self.load_damping * ones
        minv = jnp.linalg.inv(mass)
        zero, eye = jnp.zeros((n, n), w.dtype), jnp.eye(n, dtype=w.dtype)
        a = jnp.block([[zero, eye], [-matmul(minv, stiff), -matmul(minv, damp)]])
        b = jnp.concatenate([jnp.zeros(n, w.dtype), matmul(minv, jnp.ones(n, w.dtype))])[:, None]
        c = jnp.concatenate([jnp.ones(n, w.dtype), jnp.zeros(n, w.dtype)])[None, :]
        return StateSpace(a, b, c, jnp.zeros((1, 1), w.dtype))

    def truth(self, v_command: ArrayLike) -> dict[str, Array]:
        """Every noise-free signal for the commanded voltage samples `v_command` [V] (from rest): `v` (the
        amplifier's output, V), `charge_v` ($Q_V$, C), `force` ($F_c$, N), `x` (m), `strain` ($x/L$) and `charge`
        ($q$, C). Works under `jit`, `vmap` and differentiation."""
        dtype = self.capacitance.dtype
        v_cmd = bench_signal(v_command, "v_command", dtype)
        dt = jnp.asarray(1.0 / self.sample_rate, dtype)
        v = lag(v_cmd, dt, self.hv_time_constant)
        hyst = self.hysteresis(v) - self.hysteresis(jnp.zeros((1,), dtype))[0]
        q_v = self.capacitance * v + hyst
        force = self.coupling / self.capacitance * (1 + self.coupling_variation * jnp.tanh(v / self.coupling_voltage))
        force = force * q_v
        force = force + lag_sum(jnp.reshape(self.creep_fraction, (1,)), jnp.reshape(self.creep_time, (1,)), force,
                                dt, "foh")
        x = self.mechanics().simulate(force, dt, hold="foh")
        return dict(v=v, charge_v=q_v, force=force, x=x, strain=x / self.length, charge=q_v + self.coupling * x)

    def charge(self, v_out: ArrayLike) -> Array:
        """The charge [C] a charge-amplifier output `v_out` [V] stands for: $-C_f v_{out}$."""
        return -self.feedback_capacitance * jnp.asarray(v_out)

    def record(self, v_command: ArrayLike, key: PRNGKeyArray) -> Record:
        """Simulate one record for the commanded voltage samples `v_command` [V] (from rest), seeded by `key`.

        Works under `eqx.filter_jit` and `jax.vmap` (over commands and keys).

        **Returns:** a `Record` with `t`, `v_in`, `v_out` (the charge amplifier), `displacement` ($x$, m) and the
        noise-free `true_v_in`, `true_displacement` (`force` None: the wafer has no force sensor).
        """
        tr = self.truth(v_command)
        dtype = tr["x"].dtype
        t = jnp.arange(tr["x"].shape[0], dtype=dtype) / self.sample_rate
        k1, k2, k3 = jax.random.split(key, 3)
        bits = self.adc_bits
        quant = (lambda x, k, s, g: measure(x, k, s, bits, 10.0, g)) if bits else (
            lambda x, k, s, g: x + s * jax.random.normal(k, x.shape, x.dtype))
        v_out = -tr["charge"] / self.feedback_capacitance
        return Record(
            t=t,
            v_in=quant(tr["v"], k1, self.v_in_noise, 1 / 200),
            v_out=quant(v_out, k2, self.charge_noise / self.feedback_capacitance, 1.0),
            displacement=quant(tr["x"], k3, self.strain_noise * self.length, 4e5),
            force=None,
            true_v_in=tr["v"],
            true_displacement=tr["x"],
            true_force=None,
        )

