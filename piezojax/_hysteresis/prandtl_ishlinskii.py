r"""The Prandtl–Ishlinskii operator (weighted superposition of play operators) and its analytic inverse."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    as_float_array,
    check_finite,
    check_same_shape,
    check_scalar,
    check_value,
    check_vector,
)
from .._config import use_parallel_scan
from .._custom_types import ScalarLike, VectorLike
from .._dtypes import matmul, param_dtype
from .._parametrisation import setting
from .base import AbstractHysteresis, root_finding_inverse
from .play import (
    _AbstractStopCell,
    _tangent_or_none,
    check_smoothing,
    error_if_bad_smoothing,
    exact_flag,
    input_tangent_scan,
    scan_exact_or_smooth,
    sensitivity_scan,
    state_tangent,
    stop_update,
    stop_values_parallel,
)


def _thresholds_ok(thresholds: Array) -> Array:
    """True if `thresholds` is finite, non-negative and strictly ascending."""
    ok = jnp.all(jnp.isfinite(thresholds) & (thresholds >= 0))
    if thresholds.shape[0] > 1:
        ok = ok & jnp.all(jnp.diff(thresholds) > 0)
    return ok


_THRESHOLDS_MESSAGE = "`thresholds` must be finite, >= 0 and strictly ascending"


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def pi_scan(
    exact: bool | None, w0: Array, weights: Array, r: Array, smoothing: Array, v0: Array, z0: Array, signal: Array
):
    r"""Run a Prandtl–Ishlinskii operator over `signal` from the state `(v0, z0)`; return `(z_T, y)`.

    `exact`: True, False, or None to choose by `lax.cond` on `smoothing == 0` (inside, so `jax.jacfwd` batches no
    `cond` and its output needs no transposition).

    $y_k = w_0 v_k + \sum_i w_i (v_k - z_{i,k})$ with the stop values $z_{i,k}$ of `stop_scan`. Derivatives use the
    hand-derived forward sensitivities of `play.sensitivity_scan`: with $R_{i,k} = \partial z_{i,k}/\partial r_i$ and
    $S_{i,k} = \partial z_{i,k}/\partial s$ (one scan, independent of the number of tangent directions),
    $\dot y_k = \dot w_0 v_k + \sum_i \dot w_i (v_k - z_{i,k}) - \sum_i w_i (R_{i,k}\dot r_i + S_{i,k}\dot s)
    + (w_0 + \sum_i w_i)\dot v_k - \sum_i w_i \dot z^{v}_{i,k}$, where $\dot z^{v}$ (initial-state and input
    tangents) is skipped when those tangents are symbolic zeros; with the input's a symbolic zero (measured data), it
    is one more row of the same scan, $P_{i,k} = \partial z_{i,k}/\partial z_{i,0}$, times a factor per play
    (`play.state_tangent`); with input tangents, a recurrence of its own per direction. The values equal autodiff
    through the scan (same tie rules); the tangent is linear, so `jax.grad` works through it.
    """

    def run(exact):
        if exact and use_parallel_scan(signal.shape[0]):
            z = stop_values_parallel(r, v0, z0, signal)
            return z[-1], w0 * signal + matmul(signal[:, None] - z, weights)

        def body(carry, v):
            v_prev, z = carry
            z = stop_update(z, v - v_prev, r, smoothing, exact)
            return (v, z), w0 * v + matmul(weights, v - z)

        (_, z_last), y = jax.lax.scan(body, (v0, z0), signal)
        return z_last, y

    return scan_exact_or_smooth(exact, smoothing, run)


@functools.partial(pi_scan.defjvp, symbolic_zeros=True)
def _pi_scan_jvp(exact, primals, tangents):
    w0, w, r, smoothing, v0, z0, signal = primals
    dw0, dw, dr, ds, dv0, dz0, dv = (_tangent_or_none(t) for t in tangents)
    ds = None if exact is True else ds
    # initial-state tangents alone (a fitted prehistory before measured data): the row P = dz/dz0 of the one scan,
    # in the product below (`state_tangent`); with input tangents, their own recurrence (one per direction)
    with_state = dv is None and not (dv0 is None and dz0 is None)
    with_inputs = dv is not None
    carry, rows, ab = sensitivity_scan(
        r, smoothing, v0, z0, signal, exact, dr is not None, ds is not None, with_inputs, with_play=True,
        with_state=with_state,
    )
    length = signal.shape[0]
    y = w0 * signal + matmul(rows[:, 0], w)
    # one matrix product for every parameter direction: rows [play, R, S, P] against [dw, -w dr, -w ds, -w dz_s]
    coeffs = [jnp.zeros_like(w) if dw is None else dw]
    dz_last = jnp.zeros_like(z0)
    k = 1
    dz_s = state_tangent(r, smoothing, v0, z0, signal, exact, dv0, dz0) if with_state else None
    for d in (dr, ds, dz_s):
        if d is not None:
            coeffs.append(-w * d)
            dz_last = dz_last + carry[k] * d
            k += 1
    columns = rows.reshape(length, -1)
    if dw0 is not None:
        # in the same product: a separate `signal * dw0` is batched as (direction, time) under `jax.jacfwd`, the
        # product as (time, direction), and adding them costs a transposition larger than the product itself
        columns = jnp.concatenate([signal[:, None], columns], axis=1)
        coeffs.insert(0, dw0[None])
    dy = matmul(columns, jnp.concatenate(coeffs))
    if with_inputs:
        dz_in_last, dz_in = input_tangent_scan(ab, dz0, dv0, dv, signal.shape, signal.dtype)
        dy = dy - matmul(dz_in, w)
        dz_last = dz_last + dz_in_last
        dy = dy + (w0 + jnp.sum(w)) * dv
    return (carry[0], y), (dz_last, dy)


class PrandtlIshlinskii(_AbstractStopCell):
    r"""The Prandtl–Ishlinskii hysteresis operator: a linear term plus weighted play operators.

    $H[v] = w_0 v + \sum_{i=1}^{n} w_i P_{r_i}[v]$ with $0 \leq r_1 < \dots < r_n$ (paper 001 eq. 7–8, where
    $n = 15$), each play $P_{r_i}$ as in `PlayOperator`, started from the demagnetised state. Weights may have any
    sign here (the inverse operator has negative ones); keep them positive when fitting by reparametrisation. With
    `smoothing` $s > 0$ every play uses the smooth rate-independent law of `play_step` (boundary layer $s r_i$);
    $s \approx 0.1$ is a good start for fitting, continued to 0. Works under `jit`, `vmap`, `jax.grad` and
    `jax.jacfwd`; derivatives at exact ties follow `clip_stop` (e.g. $\partial H/\partial v$ includes $w_i$ fully for
    a zero threshold). They come from hand-derived forward sensitivities (`pi_scan`): one scan computes
    $\partial z_i/\partial r_i$ (and $\partial z_i/\partial s$) for every tangent direction at once, so `jax.jacfwd`
    batches a matrix product instead of the scan body (same values as autodiff through the scan; timings in
    `experiments/bench_hysteresis.py`). The exact operator (`smoothing` = 0, concrete or traced) runs as one fused
    loop on XLA:CPU; the smooth one is about 10-20x slower per sample.

    **Arguments:**

    - `weights`: $w_i$, shape `(n,)`, finite.
    - `thresholds`: $r_i$, shape `(n,)`, finite, non-negative and strictly ascending.
    - `w0`: the weight of the linear term (a play with $r = 0$), a finite scalar.
    - `smoothing`: relative smoothing $s \geq 0$ (array field); 0 = exact.

    Invalid arguments (complex or boolean, NaN/inf, out of range) raise `PiezojaxValueError` naming the argument, or
    fail under `jit` with `eqx.error_if`; see `AbstractHysteresis`.

    **Returns:** called on a signal of shape `(time,)`, the output of shape `(time,)`.

    ```python
    pi = PrandtlIshlinskii(jnp.array([1.0, 2.0]), jnp.array([0.5, 1.0]), w0=0.5)
    y = pi(jnp.array([1.0, 2.0, 1.0, 0.0, 1.0]))  # [1.0, 4.5, 4.0, 2.5, 3.0]
    v = pi.inverse()(y)                            # back to the input
    ```
    """

    weights: Float[Array, " n"]
    thresholds: Float[Array, " n"]
    w0: Float[Array, ""]
    smoothing: Float[Array, ""] = setting()

    def __init__(
        self,
        weights: VectorLike,
        thresholds: VectorLike,
        w0: ScalarLike = 1.0,
        smoothing: ScalarLike = 0.0,
    ):
        dtype = param_dtype(weights, thresholds, w0, smoothing)
        self.weights = check_vector(weights, "weights", dtype)
        thresholds = check_vector(thresholds, "thresholds", dtype, finite=False)
        if self.weights.shape != thresholds.shape:
            raise PiezojaxValueError(
                f"`weights` and `thresholds` must have the same shape, got {tuple(self.weights.shape)} and "
                f"{tuple(thresholds.shape)}"
            )
        self.thresholds = check_value(thresholds, _thresholds_ok, _THRESHOLDS_MESSAGE)
        self.w0 = check_scalar(w0, "w0", dtype)
        self.smoothing = check_smoothing(smoothing, dtype)

    def check(self) -> "PrandtlIshlinskii":
        # outside the scan: one check per parameter array, also for leaves replaced after __init__ (`eqx.tree_at`)
        check_same_shape(self.weights, "weights", self.thresholds, "thresholds")
        return eqx.tree_at(
            lambda m: (m.weights, m.thresholds, m.w0, m.smoothing),
            self,
            (
                check_finite(self.weights, "weights"),
                check_value(self.thresholds, _thresholds_ok, _THRESHOLDS_MESSAGE),
                check_finite(self.w0, "w0"),
                error_if_bad_smoothing(self.smoothing),
            ),
        )

    def _output(self, v, z):
        # state and update are the shared stop cell's; the plays are v - z
        return self.w0 * v + matmul(self.weights, v - z)

    def _run(self, state, signal):
        # One scan with hand-derived forward sensitivities (`pi_scan`): `jax.jacfwd` batches a matrix product, not
        # the scan body. `_run_autodiff` is the plain-autodiff reference.
        v0, z0 = state
        exact = exact_flag(self.smoothing)
        z_last, y = pi_scan(exact, self.w0, self.weights, self.thresholds, self.smoothing, v0, z0, signal)
        return (signal[-1], z_last), y

    def loading_curve(self, v: ArrayLike) -> Array:
        r"""The initial loading curve $\varphi(v) = w_0 v + \sum_i w_i \max(v - r_i, 0)$ for $v \geq 0$.

        It is the output of the exact operator on a monotone input rising from the demagnetised state, and it
        determines the operator (odd extension for $v < 0$ is not implied).

        **Arguments:**

        - `v`: input value(s) $\geq 0$, any shape.

        **Returns:** $\varphi(v)$, the shape of `v`.
        """
        v = as_float_array(v, "v", self.thresholds.dtype)
        return self.w0 * v + jnp.sum(self.weights * jnp.maximum(v[..., None] - self.thresholds, 0), axis=-1)

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> "AbstractHysteresis":
        r"""The analytic inverse operator, itself a Prandtl–Ishlinskii operator (Krasnosel'skii–Pokrovskii, Kuhnen).

        With an input range (`lower`, `upper`), the bounded root-finding inverse (`root_finding_inverse`)
        instead (outputs out of reach saturate at the bounds; any smoothing); without, the analytic one below.

        With $w_0$ the weight of a play at $r_0 = 0$ and slopes $a_j = w_0 + \sum_{i \leq j} w_i$ of the loading curve,
        the inverse has the inverse loading curve, i.e. thresholds and weights
        $r'_j = \sum_{i=0}^{j} w_i (r_j - r_i) = \sum_{k=1}^{j} a_{k-1}(r_k - r_{k-1})$,
        $w'_0 = 1/w_0$, $w'_j = -w_j / (a_j a_{j-1})$. Both operators start from the demagnetised state, where
        $H^{-1}[H[v]] = v$ and $H[H^{-1}[y]] = y$ for every input.

        Valid only for the exact operator (`smoothing` = 0) and when every partial sum $a_j > 0$ (a strictly
        increasing loading curve); otherwise a `ValueError` (concrete values) or an `eqx.error_if` error (traced
        values) naming `weights` (or `w0`, `smoothing`).

        **Returns:** the inverse `PrandtlIshlinskii` (with `smoothing` = 0).

        ```python
        pi = PrandtlIshlinskii(jnp.array([0.3, 0.2]), jnp.array([0.1, 0.4]), w0=1.0)
        v = pi.inverse()(y_desired)  # feedforward compensation: pi(v) == y_desired
        ```
        """
        if lower is not None or upper is not None:
            return root_finding_inverse(self, lower, upper, max_iterations)
        w0, w, r, s = self.w0, self.weights, self.thresholds, self.smoothing
        slopes = w0 + jnp.cumsum(w)  # a_1 .. a_n
        slopes_prev = jnp.concatenate([w0[None], slopes[:-1]])  # a_0 .. a_{n-1}

        s = check_value(
            s, lambda x: x == 0, "`smoothing` must be 0 for the analytic inverse (it inverts the exact operator)"
        )
        w0 = check_value(
            w0, lambda x: x > 0, "`w0` must be > 0 for the inverse to exist (strictly increasing loading curve)"
        )
        slopes = check_value(
            slopes,
            lambda x: jnp.all(x > 0),
            "`weights`: every partial sum w0 + w_1 + ... + w_j must be > 0 for the inverse to exist",
        )

        r_prev = jnp.concatenate([jnp.zeros((1,), r.dtype), r[:-1]])
        new_thresholds = jnp.cumsum(slopes_prev * (r - r_prev))  # sum of non-negative terms: no cancellation
        new_weights = -w / (slopes * slopes_prev)
        return PrandtlIshlinskii(new_weights, new_thresholds, w0=1 / w0, smoothing=s * 0)  # s * 0 keeps the check on s
