"""The creep block interface shared by every linear creep model."""

import abc

import equinox as eqx
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, check_scalar, check_signal, check_step
from .._custom_types import Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype


class AbstractCreep(eqx.Module):
    r"""A linear, time-invariant creep operator $y = \mathcal{C}[u]$ acting on a sampled signal.

    Every creep block is linear in its input and is defined by its continuous-time step response $h(t)$:
    the system is at rest with $u = 0$ before the first sample, and the output is that of the continuous-time
    operator driven by the sampled input held between samples (`hold`). Blocks with a finite state (LTI transfer
    function, Kelvin–Voigt chain) are simulated by exact discretisation; the logarithmic law has infinite memory
    and is simulated by an FFT convolution.

    `simulate(u, dt)` (also `__call__`) returns the output samples; `step_response(t)` the analytic $h(t)$;
    `instantaneous_gain()` is $h(0^+)$, which is 1 for a DC-normalised creep used in series after the hysteresis
    and 0 for a creep-only part used in parallel with it (see `Actuator`); `settled_gain()` is $h(\infty)$, the
    output per unit of an input held long enough for the creep to settle.

    Initial state: `simulate(u, dt, u0=c)` starts the block settled at the input $c$ (held since long before the
    record): the output is $h(\infty)\,c + \mathcal{C}[u - c]$.
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

    @abc.abstractmethod
    def settled_gain(self) -> Array:
        r"""$h(\infty)$: the output per unit of an input held until the creep has settled (the static gain).

        The logarithmic law never settles: its value is a convention (see `LogarithmicCreep.settled_gain`)."""

    def _dtype(self):
        return module_float_dtype(self)

    @abc.abstractmethod
    def check(self) -> "AbstractCreep":
        """Return `self` with its parameter value checks attached (`check_value`: raised now if concrete,
        `eqx.error_if` if traced), run by `simulate` outside the scan; a block without value checks returns `self`."""

    def simulate(self, u: SignalLike, dt: ArrayLike, hold: str = "zoh", u0: ArrayLike | None = None) -> Signal:
        """Response to the sampled input `u` (step `dt`), from rest or settled at the input `u0`.

        **Arguments:**

        - `u`: 1-D real, finite input samples, shape `(time,)`; use `jax.vmap` for a batch.
        - `dt`: the sample step (scalar > 0).
        - `hold`: how the input moves between samples: `"zoh"` (held constant) or `"foh"` (linear).
        - `u0`: the input held before the record, long enough for the creep to settle (a real, finite scalar):
          the output is `settled_gain() * u0 + C[u - u0]`. Default `None`: at rest with zero input (the same as
          `u0=0`).

        **Returns:** the output samples, shape `(time,)`.
        """
        if hold not in ("zoh", "foh"):
            raise PiezojaxValueError(f'`hold` must be "zoh" or "foh", got {hold!r}')
        dtype = module_float_dtype(self, u, dt)
        u = check_signal(u, "u", dtype)
        dt = check_step(dt, "dt", dtype)
        block = cast_module(self, dtype).check()
        if u0 is None:
            return block._simulate(u, dt, hold)
        u0 = check_scalar(u0, "u0", dtype)
        return block.settled_gain() * u0 + block._simulate(u - u0, dt, hold)

    def __call__(self, u: SignalLike, dt: ArrayLike, hold: str = "zoh", u0: ArrayLike | None = None) -> Signal:
        """Same as `simulate`."""
        return self.simulate(u, dt, hold, u0)


class AbstractFusedCreep(AbstractCreep):
    """A creep block with a finite state that can run inside `pj.Actuator`'s one-loop forward pass (every block's
    per-sample update in one `lax.scan`; see `pj.Actuator.simulate`). Subclass it, instead of `AbstractCreep`, and
    define `zoh_cell` to have your own block take that pass."""

    @abc.abstractmethod
    def zoh_cell(self, dt: Array):
        """The block sampled with a zero-order hold at step `dt`: a cell with `order` (the state's size) and
        `step(x, u_k) -> (x_next, y_k)` from the zero state (`pj.DiscreteStateSpace` is one). Called on a checked
        block, inside the traced forward pass."""
