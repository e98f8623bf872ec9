"""The hysteresis cell interface shared by every rate-independent operator."""

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, PyTree

from .._checks import PiezojaxValueError, check_scalar, check_signal, check_value
from .._custom_types import AbstractCell, ScalarLike, Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype, param_dtype


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
    return HysteresisInverse(op, lower, upper, max_iterations)


class AbstractFusedHysteresis(AbstractHysteresis):
    """A hysteresis operator that can run inside `pj.Actuator`'s one-loop forward pass (every block's per-sample
    update in one `lax.scan`, when its `smoothing` is a concrete 0; see `pj.Actuator.simulate`). Subclass it, instead
    of `AbstractHysteresis`, and define `exact_step` to have your own operator take that pass."""

    @abc.abstractmethod
    def exact_step(self) -> Callable | None:
        """The exact per-sample update, `step(state, v) -> (state, y)` from `init()`'s state, without checks (the
        pass checks the operator first); or None where this instance has none (an output map of an operator without
        one)."""


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


class AbstractOutputMap(AbstractFusedHysteresis):
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

    def exact_step(self) -> Callable | None:
        inner = self.hysteresis.exact_step() if isinstance(self.hysteresis, AbstractFusedHysteresis) else None
        if inner is None:
            return None

        def step(state, v):
            state, h = inner(state, v)
            return state, self.shape(h)

        return step

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        """The root-finding inverse of the whole map (`root_finding_inverse`)."""
        return root_finding_inverse(self, lower, upper, max_iterations)


# ------------------------------------------------------------------------------- the root-finding inverse


def _stop_gradient(tree: PyTree) -> PyTree:
    return jtu.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


class HysteresisInverse(AbstractHysteresisCell):
    r"""The inverse $v = \mathcal{H}^{-1}[y]$ of a hysteresis operator, by root finding at every sample.

    At sample $k$ the forward operator is in the state $s_{k-1}$ (from the inputs found so far), and its output for
    the next input $v$ is $g_k(v) = $ `hysteresis.step(s_{k-1}, v)[1]` (the straight line from $v_{k-1}$ to $v$).
    For a rate-independent operator whose output does not decrease as the input rises along such a line (a
    *monotone* operator: PI with non-negative partial sums, Maxwell slip, Preisach with $\mu \ge 0$, Bouc–Wen with
    $d$ above the largest slope of $z$, see below; decreasing ones are handled too), $g_k$ is monotone on
    `[lower, upper]` and the equation $g_k(v) = y_k$ is solved there by Newton steps from the previous input,
    safeguarded by bisection on a bracket that always contains the root. Then $s_k$ = `step(s_{k-1}, v_k)[0]`, so
    the forward operator driven by the returned inputs reproduces $y$ exactly at the samples:
    $\mathcal{H}[\mathcal{H}^{-1}[y]] = y$.

    **Saturation.** A target that the bracketing reaches a bound without crossing (below $g_k$(`lower`), above
    $g_k$(`upper`)) returns that bound (`lower`, `upper`): the inputs are
    the admissible range of the actuator, e.g. the amplifier's 0–150 V, and the output then follows the nearest
    reachable value. Between samples the forward operator follows the straight line in $v$, not in $y$: the
    samples are exact, the path between them is the forward operator's.

    **Accuracy.** For a continuous, strictly monotone $g_k$ the residual is at the rounding level of the forward
    operator (Newton converges in a few steps on the piecewise-linear PI and Maxwell-slip outputs and quadratically on
    Bouc–Wen); the iteration stops when $|g_k(v) - y_k| \le 8\varepsilon(|y_k| + |g_k(v_{k-1})| +
    |g_k'(v_{k-1})|(\text{upper} - \text{lower}))$ or the bracket is narrower than $4\varepsilon\,$(`upper` $-$ `lower`), or after
    `max_iterations`. Where $g_k$ is flat (a dead zone) any input on the flat part is returned. Where it jumps (the
    exact `Preisach`, whose output is piecewise constant in the input), the root is the switching input, found to
    the bracket tolerance, and $\mathcal{H}[\mathcal{H}^{-1}[y]]$ is the output level there: within the largest
    relay weight of $y$ (use `smoothing` > 0 for a continuous inverse).

    **Derivatives.** The root is found without tracing derivatives; the returned input carries the exact first
    derivatives of the implicit function $g_k(v_k; \theta, s_{k-1}) = y_k$: $\dot v_k = (\dot y_k - \partial_\theta
    g_k\,\dot\theta - \partial_s g_k\,\dot s_{k-1}) / \partial_v g_k$ (zero where $\partial_v g_k = 0$ and for a
    saturated sample), with the state carried through the forward `step`. So `jax.grad` and `jax.jacfwd` with
    respect to the operator's parameters and the target work through a whole signal (second derivatives do not).
    Works under `jit` and `vmap`.

    **Bouc–Wen.** $y = d\,v - z$ has $dy/dv = d - f(w)$ along an increment, with $f \le \max(A, 2\beta A /
    (\beta + \gamma))$ from the relaxed state ($n = 1$; see `BoucWen`): monotone for $d$ above that bound.

    The state is `(state of the forward operator, previous input)`, from `init()`: the forward operator's
    `init()` and input 0. To invert from another state of the forward operator `s`, pass `(s, v)` with `v` the input
    at which that state was reached.

    **Arguments:**

    - `hysteresis`: the forward operator (an `AbstractHysteresis`).
    - `lower`, `upper`: the admissible input range, finite, `lower < upper`.
    - `max_iterations` (static): iterations per sample at most in each phase, default 100 (bisection alone needs
      about 55 in float64 from the whole range).

    **Returns:** called on a target output of shape `(time,)`, the input, shape `(time,)`.

    ```python
    op = pj.BoucWen(A=0.8, beta=0.03, gamma=0.01, d=1.3)   # d > max(A, 2 beta A / (beta + gamma)) = 1.2
    inv = op.inverse(lower=-100.0, upper=100.0)             # a HysteresisInverse
    v = inv(y_desired)                                     # op(v) == y_desired at every sample
    ```
    """

    hysteresis: AbstractHysteresis
    lower: Array
    upper: Array
    max_iterations: int = eqx.field(static=True)

    def __init__(
        self, hysteresis: AbstractHysteresis, lower: ScalarLike, upper: ScalarLike, max_iterations: int = 100
    ):
        if not isinstance(hysteresis, AbstractHysteresis):
            raise PiezojaxValueError(f"`hysteresis` must be an AbstractHysteresis, got {type(hysteresis).__name__}")
        if lower is None or upper is None:
            raise PiezojaxValueError(
                "`lower` and `upper` (the admissible input range) are needed for the root-finding inverse of "
                f"{type(hysteresis).__name__}"
            )
        dtype = param_dtype(lower, upper, *jtu.tree_leaves(eqx.filter(hysteresis, eqx.is_inexact_array)))
        lower = check_scalar(lower, "lower", dtype)
        upper = check_scalar(upper, "upper", dtype)
        self.lower, self.upper = check_value((lower, upper), lambda p: p[0] < p[1], "`lower` must be < `upper`")
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
            raise PiezojaxValueError(f"`max_iterations` must be a positive int, got {max_iterations!r}")
        self.hysteresis = hysteresis
        self.max_iterations = max_iterations

    @property
    def smoothing(self) -> Array:
        """The forward operator's `smoothing`."""
        return self.hysteresis.smoothing

    def check(self) -> "HysteresisInverse":
        bounds = check_value((self.lower, self.upper), lambda p: p[0] < p[1], "`lower` must be < `upper`")
        out = eqx.tree_at(lambda m: (m.lower, m.upper), self, bounds)
        return eqx.tree_at(lambda m: m.hysteresis, out, self.hysteresis.check())

    def init(self) -> tuple[PyTree[Array], Array]:
        """`(hysteresis.init(), 0)`: the forward operator's initial state and the input it was reached at."""
        return self.hysteresis.init(), jnp.zeros((), self.lower.dtype)

    def step(self, state, y):
        op_state, v_prev = state
        y = jnp.asarray(y, self.lower.dtype)
        v = self._solve(op_state, v_prev, y)
        op_state, _ = self.hysteresis.step(op_state, v)
        return (op_state, v), v

    def _solve(self, op_state, v_prev, y):
        op, lo, hi = self.hysteresis, self.lower, self.upper
        op_c, state_c, y_c, lo_c, hi_c = _stop_gradient((op, op_state, y, lo, hi))
        eps = jnp.finfo(lo.dtype).eps

        def g(v):
            return op_c.step(state_c, v)[1] - y_c

        # The monotone direction from the slope at the previous input (or, where that is flat, from the whole range);
        # a decreasing operator is solved as its negative.
        x0 = jnp.clip(_stop_gradient(v_prev), lo_c, hi_c)
        g0, dg0 = jax.jvp(g, (x0,), (jnp.ones_like(x0),))
        rising = jnp.where(dg0 != 0, dg0 > 0, g(hi_c) >= g(lo_c))
        sign = jnp.where(rising, jnp.ones_like(g0), -jnp.ones_like(g0))

        def f(v):
            return sign * g(v)

        f0, df0 = sign * g0, sign * dg0
        ftol = 8 * eps * (jnp.abs(y_c) + jnp.abs(g0) + jnp.abs(dg0) * (hi_c - lo_c))
        xtol = 4 * eps * (hi_c - lo_c)
        # Phase 1: bracket the root by steps from the previous input, each 4x the last, starting at 1.5x the
        # Newton step: trial inputs stay near the answer (operators integrated per step, e.g. Bouc-Wen by RK4,
        # are accurate for short steps only), and a target out of reach ends at the bound it saturates at.
        up = f0 < 0
        direction = jnp.where(up, jnp.ones_like(x0), -jnp.ones_like(x0))
        bound = jnp.where(up, hi_c, lo_c)
        newton0 = jnp.abs(f0) / jnp.where(df0 > 0, df0, jnp.ones_like(df0))
        # at the previous input the slope is one-sided (a reversal can be 10x flatter): at most 5 % of the range
        step0 = jnp.where(df0 > 0, 1.5 * newton0, 1e-3 * (hi_c - lo_c))
        step0 = jnp.clip(step0, 1e-9 * (hi_c - lo_c), 0.05 * (hi_c - lo_c))

        def expand_cond(carry):
            i, near, far, crossed, _ = carry
            return (i < self.max_iterations) & ~crossed & (near != bound) & (jnp.abs(f0) > ftol)

        def expand(carry):
            i, near, far, _, step = carry
            trial = jnp.clip(near + direction * step, lo_c, hi_c)
            ft = f(trial)
            # a non-finite output (a step too long for the operator's integrator) is treated as beyond the root
            crossed = (direction * ft >= 0) | ~jnp.isfinite(ft)
            return i + 1, jnp.where(crossed, near, trial), trial, crossed, 4 * step

        i1, near, far, crossed, _ = jax.lax.while_loop(
            expand_cond, expand, (jnp.zeros((), jnp.int32), x0, x0, jnp.zeros((), bool), step0)
        )
        saturated = ~crossed & (near == bound) & (jnp.abs(f0) > ftol)

        # Phase 2: Newton from the near end, safeguarded by bisection on the bracket [a, b], f(a) < 0 <= f(b).
        a, b = jnp.minimum(near, far), jnp.maximum(near, far)

        def cond(carry):
            i, _, _, _, done = carry
            return (i < self.max_iterations) & ~done

        def body(carry):
            i, a, b, x, _ = carry
            fx, dfx = jax.jvp(f, (x,), (jnp.ones_like(x),))
            converged = jnp.abs(fx) <= ftol
            # x replaces the near end if f(x) is on its side; a non-finite f(x) counts as the far side
            left = jnp.where(jnp.isfinite(fx), fx < 0, ~up)
            a = jnp.where(left, x, a)
            b = jnp.where(left, b, x)
            newton = x - fx / jnp.where(dfx > 0, dfx, jnp.ones_like(dfx))
            ok = (dfx > 0) & (newton > a) & (newton < b) & jnp.isfinite(fx)
            x_new = jnp.where(ok, newton, 0.5 * (a + b))
            x_new = jnp.where(converged, x, x_new)
            return i + 1, a, b, x_new, converged | (b - a <= xtol)

        done = saturated | (jnp.abs(f0) <= ftol)
        v_star = jax.lax.while_loop(cond, body, (i1, a, b, near, done))[3]
        v_star = jnp.where(jnp.abs(f0) <= ftol, x0, jnp.where(saturated, bound, v_star))
        below, above = saturated & ~up, saturated & up

        # First derivatives of the implicit function: value v_star, tangent -(dg - dy) / g'(v_star).
        y_at, slope = jax.jvp(lambda v: op.step(op_state, v)[1], (v_star,), (jnp.ones_like(v_star),))
        slope = jax.lax.stop_gradient(slope)
        residual = y_at - y
        active = (jnp.abs(slope) > 0) & ~below & ~above
        correction = (residual - jax.lax.stop_gradient(residual)) / jnp.where(active, slope, jnp.ones_like(slope))
        return v_star - jnp.where(active, correction, jnp.zeros_like(correction))
