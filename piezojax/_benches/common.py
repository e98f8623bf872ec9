"""Shared pieces of the virtual benches: the bench interface, the record type, acquisition (noise, ADC) and drive
signals."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import PiezojaxValueError, as_float_array, check_finite, check_signal
from .._creep.lags import lag_sum
from .._observers.base import AbstractObserver


class Record(eqx.Module):
    """One bench record: the channels a lab would store, plus the noise-free truth for checking estimators.

    Channels are 1-D arrays on the uniform grid `t` [s]; a channel the bench does not have is `None`.

    - `v_in` [V]: the measured drive voltage (monitor output of the amplifier, noisy, quantised).
    - `v_out` [V]: the sensing-circuit output (transimpedance, integrator, or charge amplifier `V_s`).
    - `displacement` [m], `force` [N]: the reference sensors (noisy, quantised).
    - `true_v_in`, `true_displacement`, `true_force`: the same quantities without measurement errors.
    """

    t: Float[Array, " time"]
    v_in: Float[Array, " time"]
    v_out: Float[Array, " time"]
    displacement: Float[Array, " time"]
    force: Float[Array, " time"] | None
    true_v_in: Float[Array, " time"]
    true_displacement: Float[Array, " time"]
    true_force: Float[Array, " time"] | None

    @property
    def dt(self) -> Array:
        """The sample step (also for a batch of records stacked along a leading axis)."""
        return self.t[..., 1] - self.t[..., 0]


class AbstractBench(eqx.Module):
    """A seeded virtual bench: a truth model richer than the paper's model or observer, plus the lab's acquisition.

    Concrete benches define `record(command, key) -> Record` (one record from rest for the drive samples, seeded
    by `key`; works under `eqx.filter_jit` and `jax.vmap` over commands and keys) and `ideal()` (the same bench
    without noise, quantisation or drift), and carry their `sample_rate` [Hz] and converter resolution `adc_bits`
    (0: no quantisation) as static fields. Self-sensing benches add `observer(...)`
    (`AbstractSelfSensingBench`).
    """

    sample_rate: eqx.AbstractVar[float]
    adc_bits: eqx.AbstractVar[int]

    @abc.abstractmethod
    def record(self, command: ArrayLike, key: PRNGKeyArray) -> Record:
        """One record for the drive samples `command` (from rest), seeded by `key`."""

    @abc.abstractmethod
    def ideal(self) -> "AbstractBench":
        """The same bench without noise, quantisation or drift."""


class AbstractSelfSensingBench(AbstractBench):
    """A bench of a self-sensing paper: also `observer(...)`, the paper's observer with the bench's nominal
    constants."""

    @abc.abstractmethod
    def observer(self, *args, **kwargs) -> AbstractObserver:
        """The paper's observer with the bench's nominal constants."""


def bench_param(x: ArrayLike, name: str) -> Array:
    """A bench parameter: a real, finite array of the default float dtype (`PiezojaxValueError` naming `name`)."""
    return check_finite(as_float_array(x, name, jnp.zeros(()).dtype), name)


def bench_signal(x: ArrayLike, name: str, dtype) -> Array:
    """A drive signal: real, finite, 1-D with at least 2 samples (`PiezojaxValueError` naming `name`)."""
    v = check_signal(x, name, dtype)
    if v.shape[0] < 2:
        raise PiezojaxValueError(f"`{name}` must be 1-D with at least 2 samples, got shape {v.shape}")
    return v


def adc(x: Array, bits: int, full_scale: float) -> Array:
    r"""An ideal `bits`-bit converter on $[-$`full_scale`$, +$`full_scale`$]$: round to the LSB and clip."""
    lsb = 2 * full_scale / 2**bits
    return jnp.clip(jnp.round(x / lsb) * lsb, -full_scale, full_scale - lsb)


def measure(x: Array, key: PRNGKeyArray, noise: float, bits: int, full_scale: float, gain: float = 1.0) -> Array:
    """A measured channel: white Gaussian noise (std `noise`, in units of `x`), then an ADC seeing `gain * x`."""
    noisy = x + noise * jax.random.normal(key, x.shape, x.dtype)
    return adc(gain * noisy, bits, full_scale) / gain


def lag(u: Array, dt: Array, tau: ArrayLike) -> Array:
    r"""A unit-gain first-order lag $1/(1 + \tau s)$ of the interval-mean samples `u`, from rest (the benches'
    electronics): `lag_sum` with `hold="interval"`, $y_k = a y_{k-1} + (1 - a) u_k$, $a = e^{-dt/\tau}$."""
    tau = jnp.reshape(jnp.asarray(tau, u.dtype), (1,))
    return lag_sum(jnp.ones((1,), u.dtype), tau, u, dt, "interval")


def step_command(levels: ArrayLike, hold: float, sample_rate: float, rest: float = 0.0) -> np.ndarray:
    """A staircase drive: `rest` seconds at 0 V, then each of `levels` [V] held for `hold` seconds.

    **Arguments:**

    - `levels`: the voltage of each plateau, in order.
    - `hold`: duration of each plateau [s]; `sample_rate` [Hz]; `rest`: leading time at 0 V [s].

    **Returns:** a NumPy array of commanded voltage samples.

    ```python
    v = pj.step_command([100.0], hold=1000.0, sample_rate=1e3, rest=2.0)  # one 100 V step held 1000 s
    ```
    """
    levels = np.asarray(levels, dtype=float)
    if levels.ndim != 1 or levels.size == 0:
        raise PiezojaxValueError(f"`levels` must be a non-empty 1-D list of voltages, got shape {levels.shape}")
    if not (hold > 0 and sample_rate > 0 and rest >= 0):
        raise PiezojaxValueError("`hold` and `sample_rate` must be > 0 and `rest` >= 0")
    n_hold = int(round(hold * sample_rate))
    n_rest = int(round(rest * sample_rate))
    return np.concatenate([np.zeros(n_rest), np.repeat(levels, n_hold)])


def replace_fields(module: eqx.Module, **changes) -> eqx.Module:
    """A copy of `module` with some fields (static ones included) replaced, bypassing `__init__`."""
    import dataclasses

    new = object.__new__(type(module))
    for field in dataclasses.fields(module):
        object.__setattr__(new, field.name, changes.get(field.name, getattr(module, field.name)))
    return new
