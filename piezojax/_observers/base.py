"""The observer interface: electrical signals of a self-sensing circuit in, displacement (and force) estimates out."""

import abc

import equinox as eqx
from jaxtyping import Array, ArrayLike, Float


class Estimate(eqx.Module):
    """What an observer returns: the estimated `displacement` [m] and, where the paper has it, `force` [N].

    Both are 1-D signals on the input time grid; `force` is `None` for observers without a force estimate.
    """

    displacement: Float[Array, " time"]
    force: Float[Array, " time"] | None = None


class AbstractObserver(eqx.Module):
    r"""A self-sensing observer: a pure function of its parameters from (drive, circuit output) to estimates.

    Concrete observers define `__call__(v_in, v_out, dt) -> Estimate` and declare what it estimates, `estimates`:
    `("displacement",)` or `("displacement", "force")` (a class variable: the estimate's `force` is `None` exactly
    when `"force"` is not listed; a calibration reads it to know the observer's outputs). Every parameter is an
    array leaf, so an observer can be calibrated end-to-end (`jax.jacfwd` with respect to the module). `check()`
    attaches the data-dependent parameter checks (`eqx.error_if`).

    Every observer works under `jax.jit` (`eqx.filter_jit`), `jax.vmap`, `jax.grad` and `jax.jacfwd`; use float64
    for long records (the charge is a running integral of the circuit output).

    Checks: as for the circuits (`AbstractCircuit`): complex, boolean or non-finite parameters and signals raise a
    `PiezojaxValueError` naming the argument, or fail under `jit` through `eqx.error_if`.
    """

    estimates: eqx.AbstractClassVar[tuple[str, ...]]

    @abc.abstractmethod
    def check(self) -> "AbstractObserver":
        """Return `self` with its parameter value checks attached (`check_value`: raised now if concrete,
        `eqx.error_if` if traced)."""

    @abc.abstractmethod
    def __call__(self, v_in: ArrayLike, v_out: ArrayLike, dt: ArrayLike) -> Estimate:
        """Estimate displacement (and force) from the drive `v_in` and circuit output `v_out`, step `dt`."""
