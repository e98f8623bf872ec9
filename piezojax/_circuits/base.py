r"""Shared pieces of the self-sensing circuit models: the circuit interface, input checks and the sampling convention.

Sampling convention (used by every circuit and observer so that an observer inverts its circuit exactly):

- a sampled charge $Q_k = Q(t_k)$ is a point value;
- a sampled current or circuit output $I_k$ is the *mean* over the sample interval $(t_{k-1}, t_k]$, which is what an
  integrating ADC or a well anti-aliased acquisition records, so $I_k = (Q_k - Q_{k-1})/dt$ exactly;
- every record starts from rest: before the first sample the input voltage, the charge and all internal states are 0,
  so $Q_{-1} = 0$;
- a running integral $\int_0^{t_k} x\,dt$ of a sampled signal is the rectangle sum $dt \sum_{j \le k} x_j$, which is
  exact for interval means and is what a real-time (dSPACE) implementation computes.
"""

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._checks import PiezojaxValueError, check_signal, check_step
from .._custom_types import Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype


def prepare(module: eqx.Module, dt: ArrayLike, **signals: ArrayLike):
    """Validate and cast signals, `dt` and `module` to one float dtype; check that all signals have one length.

    Returns `(module, dt, signals)` with `module.check()` applied and `signals` a dict of 1-D arrays.
    """
    present = {k: v for k, v in signals.items() if v is not None}
    dtype = module_float_dtype(module, dt, *present.values())
    out = {}
    for name, x in present.items():
        out[name] = check_signal(x, name, dtype)
    lengths = {name: x.shape[0] for name, x in out.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"`{n}` has {m}" for n, m in lengths.items())
        raise PiezojaxValueError(f"channel lengths differ ({desc} samples); all channels must share one time grid")
    dt = check_step(dt, "dt", dtype)
    module = cast_module(module, dtype).check()
    for name in signals:
        out.setdefault(name, None)
    return module, dt, out


def running_integral(x: Array, dt: Array, gain: ArrayLike = 1.0, bias: ArrayLike = 0.0) -> Array:
    r"""$\int_0^{t_k} (g\,x + b)\,dt = dt\,\bigl(g \sum_{j \le k} x_j + (k + 1)\,b\bigr)$ for interval-mean samples
    `x` (see the module docstring), scalar gain $g$ and constant $b$.

    The parameters stay outside the running sum, so their derivatives need no running sum of their own: a forward-mode
    Jacobian over P directions sums the data once instead of P times (the sum was a fifth of the paper 001 observer's
    Jacobian, `python -m experiments.bench_observer`)."""
    if jnp.ndim(gain) or jnp.ndim(bias):  # a per-sample term belongs in `x`
        raise PiezojaxValueError(f"`gain` and `bias` must be scalars, got shapes {jnp.shape(gain)}, {jnp.shape(bias)}")
    steps = jnp.arange(1, x.shape[0] + 1, dtype=x.dtype)
    return dt * (gain * jnp.cumsum(x) + bias * steps)


def interval_current(q: Array, dt: Array) -> Array:
    r"""Mean current over each sample interval from point charges, from rest: $I_k = (Q_k - Q_{k-1})/dt$, $Q_{-1}=0$."""
    return jnp.diff(q, prepend=jnp.zeros((1,), q.dtype)) / dt


class AbstractCircuit(eqx.Module):
    r"""A self-sensing circuit: a forward model from the drive voltage (and mechanical inputs) to the recorded output.

    Concrete circuits define `__call__(v_in, dt, load=None) -> v_out` (the recorded output voltage, with the
    mechanical input `load` as third argument where the circuit has one) and `charge(...)` or the intermediate
    physical quantity their paper uses. Every parameter is an array leaf, so `jax.jacfwd` of the
    output with respect to the whole module gives the sensitivities a fitter needs. `check()` attaches the
    data-dependent parameter checks (`eqx.error_if`).

    Every circuit works under `jax.jit` (`eqx.filter_jit`), `jax.vmap`, `jax.grad` and `jax.jacfwd`. Running
    integrals over long records need float64 (enable x64) to keep the charge accurate.

    Checks: constructors reject complex or boolean parameters and NaN/inf or out-of-range values with a
    `PiezojaxValueError` naming the argument (`eqx.error_if` for traced values); every call rejects complex, boolean
    or non-finite signals the same way and runs `check()`.
    """

    @abc.abstractmethod
    def check(self) -> "AbstractCircuit":
        """Return `self` with its parameter value checks attached (`check_value`: raised now if concrete,
        `eqx.error_if` if traced)."""

    @abc.abstractmethod
    def __call__(self, v_in: SignalLike, dt: ArrayLike, load: SignalLike | None = None, /) -> Signal:
        """The recorded output voltage for the drive `v_in` sampled with step `dt`, shape `(time,)`.

        `load` (third, positional) is the circuit's mechanical input signal, on the drive's time grid: the
        external force `f_ext` of `ChargeIntegratorCircuit`, the stack displacement `x_a` of `SmartStackCircuit`
        (each circuit names it after that quantity, and it may be passed by that keyword). `None` (default): the
        circuit's own default (no force; the displacement from the circuit's `actuator`). A circuit without a
        mechanical input (`TransimpedanceCircuit`) raises a `PiezojaxValueError` naming `load` if one is given.
        """

