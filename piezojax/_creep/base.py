"""The creep block interface shared by every linear creep model."""

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, as_float_array, check_signal, concrete_or_none
from .._custom_types import Signal, SignalLike
from .._hysteresis.base import cast_module, module_float_dtype


def check_dt(dt: ArrayLike, dtype) -> Array:
    """Validate a sample step: a finite scalar > 0 (ValueError if concrete, `eqx.error_if` if traced)."""
    concrete = concrete_or_none(dt)  # before conversion: under jit, jnp.asarray of a number is traced
    dt = as_float_array(dt, "dt", dtype)
    if dt.ndim != 0:
        raise PiezojaxValueError(f"`dt` must be a scalar sample step, got shape {tuple(dt.shape)}")
    if concrete is not None and not (np.all(np.isfinite(concrete)) and concrete > 0):
        raise PiezojaxValueError(f"`dt` must be a finite sample step > 0, got {concrete}")
    return eqx.error_if(dt, ~(jnp.isfinite(dt) & (dt > 0)), "`dt` must be a finite sample step > 0")


def check_positive(x: ArrayLike, name: str, allow_zero: bool = False, raw: ArrayLike | None = None) -> Array:
    """Constructor check: raise naming `name` if a concrete entry is not (strictly) positive and finite.

    `raw` is the argument as the user passed it (a number stays concrete under `jit`, its `jnp.asarray` may not).
    """
    concrete = concrete_or_none(x if raw is None else raw)
    x = jnp.asarray(x)
    if concrete is not None:
        ok = (concrete >= 0) if allow_zero else (concrete > 0)
        if not (np.all(np.isfinite(concrete)) and ok.all()):
            bound = "≥ 0" if allow_zero else "> 0"
            raise PiezojaxValueError(f"`{name}` must be finite and {bound}, got {concrete}")
    return x


def error_if_not_positive(x: Array, name: str, allow_zero: bool = False) -> Array:
    """`eqx.error_if` version of `check_positive`, for values that may be traced."""
    bad = ~jnp.isfinite(x) | ((x < 0) if allow_zero else (x <= 0))
    bound = "≥ 0" if allow_zero else "> 0"
    return eqx.error_if(x, jnp.any(bad), f"`{name}` must be finite and {bound}")


class AbstractCreep(eqx.Module):
    r"""A linear, time-invariant creep operator $y = \mathcal{C}[u]$ acting on a sampled signal.

    Every creep block is linear in its input and is defined by its continuous-time step response $h(t)$:
    the system is at rest with $u = 0$ before the first sample, and the output is that of the continuous-time
    operator driven by the sampled input held between samples (`hold`). Blocks with a finite state (LTI transfer
    function, Kelvin–Voigt chain) are simulated by exact discretisation; the logarithmic law has infinite memory
    and is simulated by an FFT convolution.

    `simulate(u, dt)` (also `__call__`) returns the output samples; `step_response(t)` the analytic $h(t)$;
    `instantaneous_gain()` is $h(0^+)$, which is 1 for a DC-normalised creep used in series after the hysteresis
    and 0 for a creep-only part used in parallel with it (see `Actuator`).
    """

    @abc.abstractmethod
    def _simulate(self, u: Array, dt: Array, hold: str) -> Array:
        """Simulate with already-validated, same-dtype `u` (1-D) and `dt` (scalar > 0)."""

    @abc.abstractmethod
    def step_response(self, t: ArrayLike) -> Array:
        """The analytic continuous-time unit-step response $h(t)$ at times `t ≥ 0` (any shape)."""

    @abc.abstractmethod
    def instantaneous_gain(self) -> Array:
        """$h(0^+)$: the part of the response that follows the input without delay."""

    def check(self) -> "AbstractCreep":
        """Return `self` with data-dependent parameter checks attached (`eqx.error_if`). Default: none."""
        return self

    def simulate(self, u: SignalLike, dt: ArrayLike, hold: str = "zoh") -> Signal:
        """Response to the sampled input `u` (step `dt`), from rest.

        **Arguments:**

        - `u`: 1-D input samples, shape `(time,)`; use `jax.vmap` for a batch.
        - `dt`: the sample step (scalar > 0).
        - `hold`: how the input moves between samples: `"zoh"` (held constant) or `"foh"` (linear).

        **Returns:** the output samples, shape `(time,)`.
        """
        if hold not in ("zoh", "foh"):
            raise PiezojaxValueError(f'`hold` must be "zoh" or "foh", got {hold!r}')
        dtype = module_float_dtype(self, u, dt)
        u = check_signal(u, "u", dtype)
        dt = check_dt(dt, dtype)
        block = cast_module(self, dtype).check()
        return block._simulate(u, dt, hold)

    def __call__(self, u: SignalLike, dt: ArrayLike, hold: str = "zoh") -> Signal:
        """Same as `simulate`."""
        return self.simulate(u, dt, hold)
