r"""Play (backlash) and stop (elastic-plastic) operators, exact and smoothly relaxed.

Both operators share one state: the stop value $z = v - P_r[v] \in [-r, r]$ of each threshold. Between two input
samples the input is taken to move along a straight line, so one step advances $z$ by the input increment
$\Delta = v_k - v_{k-1}$:

- exact (paper 001 eq. 7): $z_k = \operatorname{clip}(z_{k-1} + \Delta, -r, r)$, i.e.
  $P_r[v]_k = \max(v_k - r, \min(v_k + r, P_r[v]_{k-1}))$;
- smooth, with $\varepsilon = s\,r$ for a relative smoothing $s \geq 0$: the exact flow in the input variable of
  $\mathrm{d}z/\mathrm{d}v = \min\bigl(1, (r - z)/\varepsilon\bigr)$ for increasing $v$ and
  $\mathrm{d}z/\mathrm{d}v = \min\bigl(1, (r + z)/\varepsilon\bigr)$ for decreasing $v$.

The smooth law is an ODE in $v$, not in time, and each step integrates it in closed form over the whole increment.
Its flow is a semigroup, so splitting a straight input segment into more samples changes nothing: the relaxed
operator is exactly rate-independent at every smoothing, unlike a soft clip applied once per sample. Its right-hand
side is continuous, so the result is $C^1$ in the state and in $r$ and $s$; it stays within $\varepsilon$ of the exact
operator and equals it at $s = 0$ (and for $r = 0$ at any $s$).
"""

import abc
import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, as_float_array, check_positive, check_value, concrete_or_none
from .._config import use_parallel_scan
from .._custom_types import ScalarLike
from .._dtypes import param_dtype
from .._parametrisation import setting
from .._scans import affine_scan, clamp_scan
from .base import AbstractFusedHysteresis, AbstractHysteresis, root_finding_inverse

# ---------------------------------------------------------------------------------------------------------------------
# Pure step functions (also used by other operators, e.g. the smooth Preisach form).
# ---------------------------------------------------------------------------------------------------------------------


@jax.custom_jvp
def clip_stop(z: Array, delta: Array, r: Array) -> Array:
    r"""The exact stop update $z' = \operatorname{clip}(z + \Delta, -r, r)$ for $r \geq 0$, with tie-aware derivatives.

    `jnp.clip` splits the derivative 0.5/0.5 at exact ties, so a play with $r = 0$ on a signal that starts at 0 (or
    holds a value) would give $\partial y/\partial v = 0.75$. Here, with $u = z + \Delta$, the tangent is
    $\mathrm{d}u$ strictly inside and $\pm\mathrm{d}r$ strictly outside; at a tie $u = \pm r$:

    - $r > 0$, $\Delta \neq 0$ (the input arrives exactly at a threshold): the mean of the two one-sided derivatives,
      $(\mathrm{d}u \pm \mathrm{d}r)/2$, which is what a central finite difference of the step measures;
    - $r > 0$, $\Delta = 0$ (the input holds while the play is clamped): $\mathrm{d}z + \mathrm{d}\Delta/2$, the limit
      of the smooth law as `smoothing` $\to 0$ (a chain of such ties has no linear rule that matches a central finite
      difference of the whole sequence; this one is consistent with the smooth operator);
    - $r = 0$ (then $z = \Delta = 0$): $\mathrm{d}z$, the state does not move, so $\partial P_0[v]/\partial v = 1$ and
      $\partial/\partial r$ at $r = 0$ is the one-sided derivative.

    **Arguments:**

    - `z`: previous stop state(s), in $[-r, r]$.
    - `delta`: input increment $v_k - v_{k-1}$.
    - `r`: threshold(s), $\geq 0$.

    **Returns:** the new stop state, of the broadcast shape of the arguments.
    """
    return jnp.minimum(jnp.maximum(z + delta, -r), r)


@clip_stop.defjvp
def _clip_stop_jvp(primals, tangents):
    z, delta, r = jnp.broadcast_arrays(*primals)
    dz, ddelta, dr = jnp.broadcast_arrays(*tangents)
    u = z + delta
    return jnp.minimum(jnp.maximum(u, -r), r), _clip_tangent(z, delta, r, dz, ddelta, dr)


def _flow(z, delta, r, eps):
    """Closed-form smooth flow over the increment `delta` (eps > 0), mirrored so that it always runs upwards.

    Returns `(sign, gap, q, e)` with the new state `sign * (r - gap * e)`, `q` the input travel in the boundary layer
    over `eps` and `e = exp(-q)`.
    """
    one = jnp.ones_like(z)
    sign = jnp.where(delta >= 0, one, -one)
    zs = sign * z
    d = sign * delta
    room = jnp.maximum(r - eps - zs, 0)  # input travel left in the linear region
    lin = jnp.where(d < room, d, room)
    gap = r - zs - lin
    q = (d - lin) / eps
    return sign, gap, q, jnp.exp(-q)


@jax.custom_jvp
def play_step(z: ArrayLike, delta: ArrayLike, r: ArrayLike, smoothing: ArrayLike) -> Array:
    r"""Advance the stop state $z$ of a play/stop operator by a straight input increment $\Delta$.

    Exact ($s = 0$): $z' = \operatorname{clip}(z + \Delta, -r, r)$. Smooth ($s > 0$, $\varepsilon = s r$), for
    $\Delta \geq 0$, the closed-form flow of $\mathrm{d}z/\mathrm{d}v = \min(1, (r - z)/\varepsilon)$:
    $\ell = \min(\Delta, \max(r - \varepsilon - z, 0))$, $z' = r - (r - z - \ell)\,e^{-(\Delta - \ell)/\varepsilon}$;
    for $\Delta < 0$ the mirror image $z' = -\mathrm{flow}(-z, -\Delta)$. The play output is $v_k - z'$ and the stop
    output is $z'$.

    Derivatives come from a hand-written JVP (the flow of an autonomous ODE: $\partial z'/\partial\Delta$ is the
    right-hand side at the end point, $\partial z'/\partial z = e^{-q}$, ...), exact (no NaN) at $s = 0$ and $r = 0$,
    with the tie rules of `clip_stop` for the exact operator. At $\Delta = 0$, where the smooth law switches between its
    increasing and decreasing branches, the derivative with respect to $\Delta$ is the mean of the two one-sided ones.
    The derivative with respect to `smoothing` at exactly 0 is returned as 0 (the operator is not differentiable
    there).

    **Arguments:**

    - `z`: previous stop state(s), in $[-r, r]$.
    - `delta`: input increment $v_k - v_{k-1}$ (broadcast against `z`).
    - `r`: threshold(s) $\geq 0$.
    - `smoothing`: relative smoothing $s \geq 0$; 0 is the exact operator.

    **Returns:** the new stop state(s), of the broadcast shape.

    ```python
    z = play_step(jnp.zeros(3), 0.4, jnp.array([0.0, 0.2, 1.0]), 0.0)  # [0.0, 0.2, 0.4]
    ```
    """
    z, delta, r, smoothing = jnp.broadcast_arrays(z, delta, r, smoothing)
    eps = smoothing * r
    relaxed = eps > 0
    eps_safe = jnp.where(relaxed, eps, jnp.ones_like(eps))  # the smooth branch divides by eps
    sign, gap, _, e = _flow(z, delta, r, eps_safe)
    exact = jnp.minimum(jnp.maximum(z + delta, -r), r)
    return jnp.where(relaxed, sign * (r - gap * e), exact)


@play_step.defjvp
def _play_step_jvp(primals, tangents):
    z, delta, r, smoothing = jnp.broadcast_arrays(*primals)
    dz, ddelta, dr, ds = jnp.broadcast_arrays(*tangents)
    one = jnp.ones_like(z)
    eps = smoothing * r
    relaxed = eps > 0
    eps_safe = jnp.where(relaxed, eps, one)
    sign, gap, q, e = _flow(z, delta, r, eps_safe)
    smooth = sign * (r - gap * e)
    exact = jnp.minimum(jnp.maximum(z + delta, -r), r)
    out = jnp.where(relaxed, smooth, exact)

    # Smooth flow F(z_s, d; r, eps) = r - gap * e in the mirrored frame (z_s = sign z, d = sign delta):
    # dF/dz_s = e, dF/dd = min(1, gap e / eps) (the right-hand side at the end point), dF/dr = 1 - e,
    # dF/deps = -gap e q / eps; eps = s r.
    slope = jnp.minimum(one, gap * e / eps_safe)
    slope_mean = 0.5 * (jnp.minimum(one, (r - z) / eps_safe) + jnp.minimum(one, (r + z) / eps_safe))
    slope = jnp.where(delta == 0, slope_mean, slope)
    deps = smoothing * dr + r * ds
    d_smooth = sign * (1 - e) * dr + e * dz + slope * ddelta - sign * (gap * e * q / eps_safe) * deps

    d_exact = _clip_tangent(z, delta, r, dz, ddelta, dr)
    return out, jnp.where(relaxed, d_smooth, d_exact)


def _clip_tangent(z, delta, r, dz, ddelta, dr):
    """Tangent of clip(z + delta, -r, r): see `clip_stop` for the rules at ties."""
    u = z + delta
    du = dz + ddelta
    positive = r > 0
    at_tie = jnp.where(
        delta == 0,
        dz + 0.5 * ddelta,  # a held input at a clamped play: the limit of the smooth law's mean slope
        jnp.where(u > 0, 0.5 * (du + dr), 0.5 * (du - dr)),  # the input arrives exactly at the threshold
    )
    return jnp.where(
        jnp.abs(u) < r,
        du,
        jnp.where(u > r, dr, jnp.where(u < -r, -dr, jnp.where(positive, at_tie, dz))),
    )


def stop_update(z: Array, delta: Array, r: Array, smoothing: Array, exact: bool | None = None) -> Array:
    """The stop update: `clip_stop` if `exact`, the general `play_step` (exact wherever `smoothing * r` is 0) if not;
    if `exact` is None, `clip_stop` when `smoothing` is a concrete 0."""
    if exact is None:
        s = concrete_or_none(smoothing)
        if s is not None:
            exact = bool(np.all(s == 0))
    if exact:
        return clip_stop(z, delta, r)
    return play_step(z, delta, r, smoothing)


@custom_vmap
def for_every_mapped(flag: Array) -> Array:
    """`flag` itself; under `vmap` with `flag` mapped, whether it holds for every mapped element, unmapped (through
    nested maps, axis by axis)."""
    return flag


@for_every_mapped.def_vmap
def for_every_mapped_rule(axis_size, in_batched, flag):
    if in_batched[0]:
        return for_every_mapped(jnp.all(flag, axis=0)), False
    return for_every_mapped(flag), False


def exact_everywhere(smoothing: Array) -> Array:
    """The predicate of the `lax.cond` between an operator's exact and general (smooth) loops: `smoothing == 0`, and
    under `vmap` over operators with a mapped `smoothing` (a fleet of models stacked on an axis), whether it is 0 for
    every one of them, unmapped.

    Why: a `cond` on a mapped predicate runs both of its branches, here the general loop, sequential and several
    times slower per sample (README, "Fleets"), beside the exact one. A fleet mixing exact and smoothed operators
    runs the general loop for every one, which is the exact operator (values and derivatives) wherever `smoothing`
    is 0 (`play_step`)."""
    return for_every_mapped(jax.lax.stop_gradient(smoothing) == 0)


def run_exact_or_smooth(op: AbstractHysteresis, state, signal):
    """`AbstractHysteresis._run` for operators with a `smoothing` field and a `_step(state, v, exact)` method.

    XLA:CPU compiles a scan whose body touches little memory (about 1 KiB) into one fused loop, and runs bigger bodies
    op by op, at a few hundred ns per op per sample: the smooth step falls in the second class, the exact one in the
    first. So the choice between the exact and the smooth loop is made outside the loop: in Python when `smoothing`
    is concrete, else with `lax.cond` on `exact_everywhere` (a traced smoothing still does not recompile when it
    changes). The exact loop is an order of magnitude faster per sample than the general step;
    `experiments.bench_hysteresis` measures it.
    """

    def run(exact: bool):
        return jax.lax.scan(lambda c, v: op._step(c, v, exact), state, signal, unroll=op._unroll())

    s = concrete_or_none(op.smoothing)
    if s is not None:
        return run(bool(s == 0))
    return jax.lax.cond(exact_everywhere(op.smoothing), lambda: run(True), lambda: run(False))


# ---------------------------------------------------------------------------------------------------------------------
# Forward sensitivities of a whole scan: a hand-derived JVP for `jax.jacfwd` and `jax.grad`.
# ---------------------------------------------------------------------------------------------------------------------
#
# One step is z' = f(z, Δ; r, s) with the tangent dz' = a dz + b dΔ + c dr + e ds (the coefficients of the JVPs of
# `clip_stop` and `play_step`). Over a signal, the sensitivities R_k = ∂z_k/∂r and S_k = ∂z_k/∂s obey one scalar
# recurrence per threshold, R_k = a_k R_{k-1} + c_k and S_k = a_k S_{k-1} + e_k, whatever the number of tangent
# directions. One scan computes them; the output tangent is then a product of these (time, n) arrays with the
# parameter tangents, outside the scan, and `jax.jacfwd` batches only that product instead of the scan body (the
# autodiff JVP of the scan runs its body once per direction, ~30x the forward pass on XLA:CPU for a 16-play PI).
# Tangents of the initial state (v0, z0) alone (a fitted prehistory or state before measured data) take one more primal
# row, P_k = ∂z_k/∂z_init = a_k P_{k-1} (P_{-1} = 1), times a factor per threshold (`state_tangent`). Tangents of the
# input signal need a recurrence of their own (ż_k = a_k ż_{k-1} + b_k dΔ_k, one per direction); it runs only when
# they are not symbolic zeros, i.e. not for measured data.

_SymbolicZero = jax.custom_derivatives.SymbolicZero


def _tangent_or_none(t):
    return None if type(t) is _SymbolicZero else t


def step_coefficients(z: Array, delta: Array, r: Array, smoothing: Array, exact: bool):
    """One stop update and the coefficients of its tangent $dz' = a\\,dz + b\\,d\\Delta + c\\,dr + e\\,ds$.

    The same values and tie rules as the JVPs of `clip_stop` (`exact`) and `play_step` (smooth, exact wherever
    `smoothing * r` is 0). **Returns:** `(z', a, b, c, e)`, `e` None when `exact`.
    """
    one = jnp.ones_like(z)
    zero = jnp.zeros_like(z)
    half = 0.5 * one
    u = z + delta
    z_exact = jnp.minimum(jnp.maximum(u, -r), r)
    inside = jnp.abs(u) < r
    above = u > r
    below = u < -r
    moving_tie = (r > 0) & (delta != 0)  # the input arrives exactly at a threshold: mean of one-sided derivatives
    # a tie with a held input (r > 0): dz + dΔ/2; with r = 0 (u = 0): dz
    a_x = jnp.where(inside, one, jnp.where(above | below, zero, jnp.where(moving_tie, half, one)))
    b_x = jnp.where(inside, one, jnp.where(above | below, zero, jnp.where(r > 0, half, zero)))
    c_tie = jnp.where(moving_tie, jnp.where(u > 0, half, -half), zero)
    c_x = jnp.where(above, one, jnp.where(below, -one, jnp.where(inside, zero, c_tie)))
    if exact:
        return z_exact, a_x, b_x, c_x, None
    eps = smoothing * r
    relaxed = eps > 0
    eps_safe = jnp.where(relaxed, eps, one)
    sign, gap, q, e = _flow(z, delta, r, eps_safe)
    slope = jnp.minimum(one, gap * e / eps_safe)
    slope_mean = 0.5 * (jnp.minimum(one, (r - z) / eps_safe) + jnp.minimum(one, (r + z) / eps_safe))
    slope = jnp.where(delta == 0, slope_mean, slope)
    k = sign * gap * e * q / eps_safe  # -dF/deps in the original frame, with eps = s r
    return (
        jnp.where(relaxed, sign * (r - gap * e), z_exact),
        jnp.where(relaxed, e, a_x),
        jnp.where(relaxed, slope, b_x),
        jnp.where(relaxed, sign * (one - e) - k * smoothing, c_x),
        jnp.where(relaxed, -k * r, zero),
    )


def sensitivity_scan(r, smoothing, v0, z0, signal, exact, with_r, with_s, with_ab, with_play, with_state=False):
    """Scan the stop cell with the sensitivities of its state to `r` and `s` (and, `with_state`, to the initial
    stop values: $P = \\partial z/\\partial z_0$, see `state_tangent`).

    `exact`: True, False, or None to choose with `lax.cond` on `smoothing == 0` (`exact_everywhere`; the exact
    operator has $S = 0$).
    Only primal values are computed here, so under `jax.jacfwd` nothing in this scan is batched.

    **Returns:** `(carry, rows, ab)`: `carry` the final packed state `[z, R?, S?, P?]`, shape `(k, *n)`; `rows` per
    sample `[v - z if with_play else z, R?, S?, P?]`, shape `(time, k, *n)`; `ab` the coefficients `[a, b]` per
    sample, shape `(time, 2, *n)`, or None.
    """
    if exact is None:
        return jax.lax.cond(
            exact_everywhere(smoothing),
            lambda: sensitivity_scan(r, smoothing, v0, z0, signal, True, with_r, with_s, with_ab, with_play,
                                     with_state),
            lambda: sensitivity_scan(r, smoothing, v0, z0, signal, False, with_r, with_s, with_ab, with_play,
                                     with_state),
        )
    if exact and use_parallel_scan(signal.shape[0]):
        return _sensitivity_parallel(r, smoothing, v0, z0, signal, with_r, with_s, with_ab, with_play, with_state)
    init = [z0] + [jnp.zeros_like(z0)] * (int(with_r) + int(with_s)) + ([jnp.ones_like(z0)] if with_state else [])

    def body(carry, v):
        v_prev, packed = carry
        z, a, b, c, e = step_coefficients(packed[0], v - v_prev, r, smoothing, exact)
        new = [z]
        if with_r:
            new.append(a * packed[1] + c)
        if with_s:
            new.append(a * packed[1 + int(with_r)] + (jnp.zeros_like(z) if e is None else e))
        if with_state:
            new.append(a * packed[-1])
        rows = jnp.stack([v - z] + new[1:]) if with_play else jnp.stack(new)
        out = (rows, jnp.stack([a, b])) if with_ab else (rows, None)
        return (v, jnp.stack(new)), out

    (_, carry), (rows, ab) = jax.lax.scan(body, (v0, jnp.stack(init)), signal)
    return carry, rows, ab


def state_tangent(r, smoothing, v0, z0, signal, exact, dv0, dz0):
    r"""The tangent of the state `(v0, z0)` before `signal` as one factor per threshold of the row
    $P_k = \partial z_k/\partial z_{\mathrm{init}} = \prod_{j=0}^k a_j$ (`sensitivity_scan`, `with_state`):
    $\dot z_k = P_k (\dot z_{\mathrm{init}} - (b_0/a_0)\,\dot v_{\mathrm{init}})$, since only the first sample's
    increment $\Delta_0 = s_0 - v_{\mathrm{init}}$ reads $v_{\mathrm{init}}$, so that
    $\partial z_k/\partial v_{\mathrm{init}} = -b_0 \prod_{j=1}^k a_j$ ($a_j$, $b_j$ the coefficients of
    `step_coefficients` at sample $j$). Where $a_0 = 0$ the first step clamped the stop; then $b_0 = 0$ too (in
    every branch of `step_coefficients`) and the factor is $\dot z_{\mathrm{init}}$ (times $P = 0$)."""
    _, a0, b0, _, _ = step_coefficients(z0, signal[0] - v0, r, smoothing, exact is True)
    d = jnp.zeros_like(z0) if dz0 is None else dz0
    if dv0 is None:
        return d
    ratio = jnp.where(a0 != 0, b0 / jnp.where(a0 != 0, a0, 1.0), 0.0)
    return d - ratio * dv0


def _expand(signal, z):
    """`signal` (time,) with unit axes to broadcast against stop values of shape `(time, *n)`."""
    return signal.reshape(signal.shape + (1,) * (z.ndim - 1))


def stop_values_parallel(r, v0, z0, signal):
    r"""The exact stop values, shape `(time, *n)`, over `signal` (shape `(time,)`) by `clamp_scan` on the play
    output $y = v - z$: $y_k = \mathrm{clip}(y_{k-1}, v_k - r, v_k + r)$, the same recursion as `clip_stop`. A
    clamped sample's stop value is exactly $\pm r$, as the sequential update gives it (the derivative rules tell a
    tie from a clamp by it); a free one is rounded once per sample instead of carried."""
    v = _expand(signal, jnp.zeros((1,) + jnp.shape(jnp.broadcast_arrays(r, z0)[0])))
    lo, hi = v - r, v + r
    y = clamp_scan(lo, hi, v0 - z0)
    r_full = jnp.broadcast_to(r, y.shape)
    return jnp.where(y == lo, r_full, jnp.where(y == hi, -r_full, v - y))


def _sensitivity_parallel(r, smoothing, v0, z0, signal, with_r, with_s, with_ab, with_play, with_state=False):
    """`sensitivity_scan` of the exact operator in parallel in time: the stop values by `stop_values_parallel`,
    then each sample's tangent coefficients (`step_coefficients`, elementwise) and $R_k = a_k R_{k-1} + c_k$ (and
    $P$) by `affine_scan` ($S = 0$ for the exact operator)."""
    z = stop_values_parallel(r, v0, z0, signal)
    z_prev = jnp.concatenate([jnp.broadcast_to(z0, z.shape[1:])[None], z[:-1]])
    v = _expand(signal, z)
    v_prev = jnp.concatenate([jnp.reshape(v0, (1,) * v.ndim), v[:-1]])
    _, a, b, c, _ = step_coefficients(z_prev, v - v_prev, r, smoothing, True)
    new = [z]
    if with_r:
        new.append(affine_scan(a, c))
    if with_s:
        new.append(jnp.zeros_like(z))
    if with_state:
        new.append(affine_scan(a, jnp.zeros_like(z), jnp.ones_like(z[0])))
    rows = jnp.stack([v - z] + new[1:], axis=1) if with_play else jnp.stack(new, axis=1)
    carry = jnp.stack([x[-1] for x in new])
    return carry, rows, (jnp.stack([a, b], axis=1) if with_ab else None)


def input_tangent_scan(ab, dz0, dv0, dv, signal_shape, dtype):
    """The state tangent $\\dot z_k = a_k \\dot z_{k-1} + b_k (\\dot v_k - \\dot v_{k-1})$ from the tangents of the
    input signal `dv` and the initial state `(dv0, dz0)` (None for zero). Linear in them (transposable)."""
    n_shape = ab.shape[2:]
    dv = jnp.zeros(signal_shape, dtype) if dv is None else dv
    dv0 = jnp.zeros((), dtype) if dv0 is None else dv0
    dz0 = jnp.zeros(n_shape, dtype) if dz0 is None else dz0
    ddelta = jnp.diff(dv, prepend=dv0[None])

    if use_parallel_scan(ab.shape[0]):
        dz = affine_scan(ab[:, 0], ab[:, 1] * _expand(ddelta, ab[:, 0]), dz0)
        return dz[-1], dz

    def body(dz, x):
        dd, coeffs = x  # the linear input first, the residual coefficients last (scan transposition)
        dz = coeffs[0] * dz + coeffs[1] * dd
        return dz, dz

    return jax.lax.scan(body, dz0, (ddelta, ab))


def exact_flag(smoothing: Array) -> bool | None:
    """True/False for a concrete `smoothing` (0 = exact), None for a traced one (chosen later by `lax.cond`)."""
    s = concrete_or_none(smoothing)
    return None if s is None else bool(s == 0)


def scan_exact_or_smooth(exact: bool | None, smoothing: Array, run):
    """`run(True)` or `run(False)`; for `exact=None` the choice is a `lax.cond` on `exact_everywhere(smoothing)`."""
    if exact is None:
        return jax.lax.cond(exact_everywhere(smoothing), lambda: run(True), lambda: run(False))
    return run(exact)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def stop_scan(exact: bool | None, r: Array, smoothing: Array, v0: Array, z0: Array, signal: Array) -> Array:
    """The stop values $z_k$ of thresholds `r` over `signal` from the state `(v0, z0)`, shape `(time, *n)`.

    Forward pass: the exact (`exact=True`) or general (`play_step`) update in a `lax.scan` (`exact=None`: chosen by
    `lax.cond` on `smoothing == 0`, inside this function so that `jax.jacfwd` batches no `cond`). Derivatives: the
    hand-derived forward sensitivities above (identical values to autodiff through the scan, at a fraction of the
    `jax.jacfwd` cost); linear in the tangents, so `jax.grad` works too.
    """

    def run(exact):
        if exact and use_parallel_scan(signal.shape[0]):
            return stop_values_parallel(r, v0, z0, signal)

        def body(carry, v):
            v_prev, z = carry
            z = stop_update(z, v - v_prev, r, smoothing, exact)
            return (v, z), z

        return jax.lax.scan(body, (v0, z0), signal)[1]

    return scan_exact_or_smooth(exact, smoothing, run)


@functools.partial(stop_scan.defjvp, symbolic_zeros=True)
def _stop_scan_jvp(exact, primals, tangents):
    r, smoothing, v0, z0, signal = primals
    dr, ds, dv0, dz0, dv = (_tangent_or_none(t) for t in tangents)
    ds = None if exact is True else ds
    # initial-state tangents alone: the row P (no per-direction recurrence); with input tangents: their own scan
    with_state = dv is None and not (dv0 is None and dz0 is None)
    with_inputs = dv is not None
    _, rows, ab = sensitivity_scan(
        r, smoothing, v0, z0, signal, exact, dr is not None, ds is not None, with_inputs, with_play=False,
        with_state=with_state,
    )
    z = rows[:, 0]
    dz = jnp.zeros_like(z)
    k = 1
    for d in (dr, ds):
        if d is not None:
            dz = dz + rows[:, k] * d
            k += 1
    if with_state:
        dz = dz + rows[:, k] * state_tangent(r, smoothing, v0, z0, signal, exact, dv0, dz0)
    if with_inputs:
        dz = dz + input_tangent_scan(ab, dz0, dv0, dv, signal.shape, signal.dtype)[1]
    return z, dz


# ---------------------------------------------------------------------------------------------------------------------
# Shared construction helpers.
# ---------------------------------------------------------------------------------------------------------------------




def check_thresholds_shape(x: ArrayLike, name: str, dtype, allow_scalar: bool) -> Array:
    arr = as_float_array(x, name, dtype)
    if arr.ndim > 1 or (arr.ndim == 0 and not allow_scalar):
        expected = "a scalar or a 1-D array" if allow_scalar else "a 1-D array"
        raise PiezojaxValueError(f"`{name}` must be {expected}, got shape {tuple(arr.shape)}")
    if arr.ndim == 1 and arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return arr


def check_smoothing(smoothing: ScalarLike, dtype) -> Array:
    """Validate the `smoothing` argument: a real scalar, finite and >= 0 (see `error_if_bad_smoothing`)."""
    s = as_float_array(smoothing, "smoothing", dtype)
    if s.ndim != 0:
        raise PiezojaxValueError(f"`smoothing` must be a scalar, got shape {tuple(s.shape)}")
    return error_if_bad_smoothing(s)


def error_if_bad_smoothing(smoothing: Array) -> Array:
    """Check `smoothing` >= 0 and finite (`check_value`: a concrete value stays concrete for `stop_update`)."""
    return check_value(
        smoothing,
        lambda s: jnp.isfinite(s) & (s >= 0),
        "`smoothing` must be finite and >= 0 (0 = exact operator)",
    )


# ---------------------------------------------------------------------------------------------------------------------
# Operators.
# ---------------------------------------------------------------------------------------------------------------------


class _AbstractStopCell(AbstractFusedHysteresis):
    """Shared cell of the stop-value operators (play, stop, PI, Gaussian Preisach): state `(previous input, stop
    values z)`, one update law."""

    thresholds: eqx.AbstractVar[Float[Array, "*n"]]
    smoothing: eqx.AbstractVar[Float[Array, ""]]

    # every stop cell's output is 0 at v = 0 with its stops at 0 (play, stop, PI, Gaussian Preisach: w0 v +
    # sum w_j phi(v - z_j) with phi(0) = 0)
    zero_at_rest: ClassVar[bool | None] = True

    def init(self) -> tuple[Array, Array]:
        """Demagnetised state `(previous input, stop values) = (0, 0)`."""
        dtype = self.thresholds.dtype
        return jnp.zeros((), dtype), jnp.zeros(self.thresholds.shape, dtype)

    def step(self, state, v):
        return self._step(state, v, None)

    def _run_autodiff(self, state, signal):
        """`_run` differentiated by plain autodiff through the scan (the reference for the hand-derived JVP)."""
        return run_exact_or_smooth(self, state, signal)

    def exact_step(self):
        return lambda state, v: self._step(state, v, True)

    def _step(self, state, v, exact):
        v_prev, z = state
        z = stop_update(z, v - v_prev, self.thresholds, self.smoothing, exact)
        return (v, z), self._output(v, z)

    @abc.abstractmethod
    def _output(self, v: Array, z: Array) -> Array:
        """The operator's output from the input and the new stop values."""


class _AbstractPlainStopCell(_AbstractStopCell):
    """The play and stop operators: the checks of `thresholds` and `smoothing`, the loop of `stop_scan` and the
    root-finding inverse (final here)."""

    def check(self):
        return eqx.tree_at(
            lambda m: (m.thresholds, m.smoothing),
            self,
            (check_positive(self.thresholds, "thresholds", allow_zero=True), error_if_bad_smoothing(self.smoothing)),
        )

    def _run(self, state, signal):
        # The exact or smooth loop is chosen outside the scan (see `run_exact_or_smooth`); `stop_scan` carries the
        # hand-derived forward sensitivities (fast `jax.jacfwd`).
        v0, z0 = state
        z = stop_scan(exact_flag(self.smoothing), self.thresholds, self.smoothing, v0, z0, signal)
        return (signal[-1], z[-1]), jax.vmap(self._output)(signal, z)

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        return root_finding_inverse(self, lower, upper, max_iterations)


class PlayOperator(_AbstractPlainStopCell):
    r"""The play (backlash) operator $P_r$, for one threshold or a vector of thresholds at once.

    $P_r[v]_k = \max\bigl(v_k - r, \min(v_k + r, P_r[v]_{k-1})\bigr)$ (paper 001 eq. 7), started from the
    demagnetised state (input 0, output 0). With `smoothing` $s > 0$ the stop part $v - P_r[v]$ follows the smooth
    rate-independent law of `play_step` (boundary layer of width $s r$ at each threshold); $s = 0.1$ is a good value for
    fitting, continued towards 0 at the end. Works under `jit`, `vmap`, `jax.grad` and `jax.jacfwd` (derivatives by the
    hand-derived forward sensitivities of `stop_scan`, equal to autodiff through the scan).

    **Arguments:**

    - `thresholds`: $r \geq 0$, a scalar or a 1-D array of $n$ thresholds (any order).
    - `smoothing`: relative smoothing $s \geq 0$ (array field: changing it does not recompile); 0 = exact.

    **Returns:** called on a signal of shape `(time,)`, the play outputs, shape `(time, n)` (or `(time,)` for a scalar
    threshold).

    ```python
    play = PlayOperator(jnp.array([0.0, 0.5, 1.0]))
    y = play(jnp.sin(jnp.linspace(0, 10, 200)))  # shape (200, 3)
    ```
    """

    thresholds: Float[Array, "*n"]
    smoothing: Float[Array, ""] = setting()

    def __init__(self, thresholds: ArrayLike, smoothing: ScalarLike = 0.0):
        dtype = param_dtype(thresholds, smoothing)
        arr = check_thresholds_shape(thresholds, "thresholds", dtype, allow_scalar=True)
        self.thresholds = check_positive(arr, "thresholds", allow_zero=True)
        self.smoothing = check_smoothing(smoothing, dtype)

    def _output(self, v, z):
        return v - z


class StopOperator(_AbstractPlainStopCell):
    r"""The stop (elastic–perfectly-plastic) operator $S_r = I - P_r$, for one threshold or a vector of thresholds.

    $S_r[v]_k = \operatorname{clip}(S_r[v]_{k-1} + v_k - v_{k-1}, -r, r)$, started from the demagnetised state
    (input 0, output 0); with `smoothing` $s > 0$ the smooth rate-independent law of `play_step`. Works under `jit`,
    `vmap`, `jax.grad` and `jax.jacfwd`.

    **Arguments:**

    - `thresholds`: $r \geq 0$, a scalar or a 1-D array of $n$ thresholds (any order).
    - `smoothing`: relative smoothing $s \geq 0$ (array field); 0 = exact.

    **Returns:** called on a signal of shape `(time,)`, the stop outputs, shape `(time, n)` (or `(time,)`), each in
    $[-r, r]$.

    ```python
    stop = StopOperator(1.0)
    z = stop(jnp.array([0.5, 2.0, 1.0]))  # [0.5, 1.0, 0.0]
    ```
    """

    thresholds: Float[Array, "*n"]
    smoothing: Float[Array, ""] = setting()

    def __init__(self, thresholds: ArrayLike, smoothing: ScalarLike = 0.0):
        dtype = param_dtype(thresholds, smoothing)
        arr = check_thresholds_shape(thresholds, "thresholds", dtype, allow_scalar=True)
        self.thresholds = check_positive(arr, "thresholds", allow_zero=True)
        self.smoothing = check_smoothing(smoothing, dtype)

    def _output(self, v, z):
        return z


def exact_cell(op: AbstractHysteresis):
    """The exact per-sample update of `op` (`AbstractFusedHysteresis.exact_step`), or None where it has none. The
    caller makes sure `op.smoothing` is 0."""
    return op.exact_step() if isinstance(op, AbstractFusedHysteresis) else None
