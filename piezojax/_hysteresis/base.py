"""The hysteresis cell interface shared by every rate-independent operator."""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, PyTree

from .._checks import check_signal
from .._custom_types import AbstractCell, ScalarLike, Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype


class AbstractHysteresis(AbstractCell):
    r"""A rate-independent hysteresis operator $y = \mathcal{H}[v]$, written as a cell.

    A concrete operator defines `init()` (the relaxed / demagnetised state, input at 0) and
    `step(state, v) -> (state, y)`, which advances the operator from the previous input sample (kept in the state)
    to `v` along the straight line between them. Because the path between samples is a straight line, the exact
    operators are rate-independent: inserting samples on that line changes nothing at the original samples. It also
    defines `check()`, `_run` (the loop over a signal; `scan_cell` for the plain scan of `step`) and `inverse`
    (`root_finding_inverse` unless it has an analytic one).

    `smoothing` (0 = exact) selects a smooth relaxation that keeps this property; see each operator. Declare it as a
    setting, `smoothing: Array = pj.setting()`, so that a calibration does not fit it by default.

    `scan(signal, state)` runs the cell over a signal with `jax.lax.scan` and returns the final state with the
    output; `__call__(signal, state=None)` returns only the output.

    Checks: every constructor rejects parameters of the wrong shape, complex or boolean parameters, and NaN/inf or
    out-of-range values, with a `PiezojaxValueError` naming the argument; values traced under `jit`/`vmap` get the
    same check as `eqx.error_if`. The call checks the signal (real, 1-D, non-empty, finite) and runs `check()`,
    which repeats the value checks outside the scan, so parameters replaced after construction (`eqx.tree_at`, as a
    fitter does) are checked too.
    """

    smoothing: eqx.AbstractVar[Array]

    @abc.abstractmethod
    def init(self) -> PyTree[Array]:
        """The relaxed (demagnetised) initial state, with the input at 0."""

    zero_at_rest: ClassVar[bool | None] = False
    """Declare `True` when the output in the initial state `init()` at input 0 is 0 for every parameter value (the
    play and stop operators, PI, the Gaussian Preisach, Maxwell slip, Bouc–Wen); `None` (the output maps): as the
    wrapped operator. See `rests_at_zero`."""

    @property
    def rests_at_zero(self) -> bool:
        """Whether the output in the initial state at input 0 is 0 (`zero_at_rest`). `pj.Actuator` then starts
        from rest without running the operator; otherwise (default, e.g. a Preisach operator, whose demagnetised
        output $c + \\sum_i \\mu_i R_i$ need not vanish) it settles the creep and the dynamics at that output
        before the record."""
        if self.zero_at_rest is None:
            return self.hysteresis.rests_at_zero
        return bool(self.zero_at_rest)

    @abc.abstractmethod
    def step(self, state: PyTree[Array], v: Array) -> tuple[PyTree[Array], Array]:
        """Advance from the state's previous input to the input sample `v`; return `(state, y)`."""

    @abc.abstractmethod
    def check(self) -> "AbstractHysteresis":
        """Return `self` with its parameter value checks attached (`check_value`: raised now if concrete,
        `eqx.error_if` if traced); an operator without value checks returns `self`."""

    def scan(self, signal: SignalLike, state: PyTree[Array] | None = None) -> tuple[PyTree[Array], Signal]:
        """Run the operator over `signal` from `state` (default `init()`); return `(final_state, output)`.

        **Arguments:**

        - `signal`: 1-D real, finite input samples, shape `(time,)` (complex or boolean: `PiezojaxValueError`).
        - `state`: the state to start from, e.g. the final state of an earlier call. Default: `self.init()`.

        **Returns:** `(final_state, y)` with `y` of shape `(time,)`, or `(time, n)` for an operator that returns one
        output per threshold (`PlayOperator`, `StopOperator` with a vector of thresholds).
        """
        op, signal, state = self._prepare(signal, state)
        return op._run(state, signal)

    def _prepare(self, signal: SignalLike, state: PyTree[Array] | None):
        """Validate `signal`, cast the operator, signal and state to their common float dtype, attach `check()`."""
        dtype = module_float_dtype(self, signal)
        signal = check_signal(signal, "signal", dtype)
        op = cast_module(self, dtype).check()
        if state is None:
            state = op.init()
        else:
            state = jtu.tree_map(lambda s: jnp.asarray(s, dtype), state)
        return op, signal, state

    @abc.abstractmethod
    def _run(self, state: PyTree[Array], signal: Signal) -> tuple[PyTree[Array], Signal]:
        """Scan the cell over a prepared signal (checked, cast, from `state`); return `(final_state, output)`.

        Operators without a faster loop return `scan_cell(self, state, signal)`, the plain `jax.lax.scan` of `step`;
        others choose a faster loop outside the scan or carry hand-derived derivatives."""

    def __call__(self, signal: SignalLike, state: PyTree[Array] | None = None) -> Signal:
        """Apply the operator to a 1-D `signal` (see `scan`) and return the output signal."""
        return self.scan(signal, state)[1]

    @abc.abstractmethod
    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> "AbstractHysteresis":
        r"""The inverse operator $\mathcal{H}^{-1}$, for feedforward compensation: `self(inverse(y)) == y`.

        Most operators return `root_finding_inverse(self, lower, upper, max_iterations)`: per-sample root finding on
        the admissible input range (`HysteresisInverse`, whose docstring gives the conditions, the accuracy and the
        derivatives). Operators with an analytic inverse return it instead (`PrandtlIshlinskii.inverse()` without
        bounds).

        **Arguments:**

        - `lower`, `upper`: the admissible input range (finite, `lower < upper`); outputs out of reach saturate at
          these inputs. Needed by the root-finding inverse (`PiezojaxValueError` naming them if missing).
        - `max_iterations`: root-finding iterations per sample at most.

        **Returns:** an `AbstractHysteresis` mapping the desired output to the input.
        """

    def _unroll(self) -> int:
        # Measured on XLA:CPU (jax 0.10.2): unroll=1 is fastest for these small cells (unrolling slows them).
        return 1


def change_from_rest(op, v: Array, path: Array | None = None) -> Array:
    """`op(v)` less the operator's output at rest before it, for an integrator reset at rest: after `path` (e.g. a
    prehistory excursion ending at 0 V) when given, else demagnetised at 0 V, where an operator that `rests_at_zero`
    (or an `op(v)` callable without the attribute, read as given) outputs 0."""
    if path is None:
        if getattr(op, "rests_at_zero", True):
            return op(v)
        path = jnp.zeros((1,), v.dtype)
    h = op(jnp.concatenate([path.astype(v.dtype), v]))
    return h[path.shape[0]:] - h[path.shape[0] - 1]


def scan_cell(op: AbstractHysteresis, state: PyTree[Array], signal: Signal) -> tuple[PyTree[Array], Signal]:
    """The plain `_run`: `jax.lax.scan` of `op.step` over a prepared signal, from `state`."""
    # A plain closure, not the bound method: jax hashes the scan body, and a bound method of a Module hashes
    # its (unhashable) array fields.
    return jax.lax.scan(lambda carry, v: op.step(carry, v), state, signal, unroll=op._unroll())


def root_finding_inverse(
    op: AbstractHysteresis, lower: ScalarLike | None, upper: ScalarLike | None, max_iterations: int
) -> AbstractHysteresis:
    """The inverse of `op` by per-sample root finding on `[lower, upper]` (`HysteresisInverse`; see
    `AbstractHysteresis.inverse`)."""
    from .inverse import HysteresisInverse

    return HysteresisInverse(op, lower, upper, max_iterations)


class AbstractHysteresisCell(AbstractHysteresis):
    """An operator run by the plain scan of its cell and inverted by root finding: the simplest way to write one.

    Define `init()`, `step(state, v)` and `check()` (return `self` if there is nothing to check); `_run` is
    `scan_cell` and `inverse` is `root_finding_inverse` (both final here). `Preisach` and `HysteresisInverse` are
    written this way.
    """

    def _run(self, state: PyTree[Array], signal: Signal) -> tuple[PyTree[Array], Signal]:
        return scan_cell(self, state, signal)

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        return root_finding_inverse(self, lower, upper, max_iterations)


class AbstractOutputMap(AbstractHysteresis):
    """An operator followed by a static map of its output (`OutputPolynomial`, `ScaledHysteresis`).

    The state, the smoothing and the loop are the wrapped operator's: `init`, `step` and `_run` are its own with
    `shape` applied to the output, so an initial state, a prehistory or the operator's fast loop and derivatives
    work as for the operator alone, and `inverse` is the root-finding inverse of the whole map. Concrete wrappers
    define `shape` and `check`.
    """

    hysteresis: eqx.AbstractVar[AbstractHysteresis]
    # the wrapped operator's `rests_at_zero`: `shape` must send 0 to 0 (else declare `zero_at_rest = False`)
    zero_at_rest: ClassVar[bool | None] = None

    @abc.abstractmethod
    def shape(self, h: Array) -> Array:
        """The static map applied to the operator's output `h` (any shape)."""

    @property
    def smoothing(self) -> Array:
        """The wrapped operator's `smoothing`."""
        return self.hysteresis.smoothing

    def init(self) -> PyTree[Array]:
        return self.hysteresis.init()

    def step(self, state: PyTree[Array], v: Array) -> tuple[PyTree[Array], Array]:
        state, h = self.hysteresis.step(state, v)
        return state, self.shape(h)

    def _run(self, state, signal):
        state, h = self.hysteresis._run(state, signal)
        return state, self.shape(h)

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        """The root-finding inverse of the whole map (`root_finding_inverse`)."""
        return root_finding_inverse(self, lower, upper, max_iterations)
