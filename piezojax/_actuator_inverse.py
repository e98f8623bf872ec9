"""The inverse of a whole actuator (hysteresis, creep and dynamics): feedforward voltage for a desired displacement."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, PyTree

from ._checks import PiezojaxValueError, check_positive, check_signal, check_step, concrete_or_none
from ._creep.logarithmic import causal_convolution
from ._custom_types import Signal, SignalLike
from ._dtypes import cast_module, module_float_dtype
from ._hysteresis.base import AbstractHysteresis, HysteresisInverse
from ._linear.base import AbstractLinearSystem, default_inverse_bandwidth
from ._linear.delay import delay_signal


class ActuatorInverse(eqx.Module):
    r"""The voltage that makes an `Actuator` follow a desired displacement: $V = \mathcal{A}^{-1}[\delta_d]$.

    Built by `Actuator.inverse(...)`; called as `inv(displacement, dt, hold)`, it returns the voltage samples for
    `actuator.simulate(voltage, dt, hold)`. The chain is inverted block by block, from the output back:

    1. **Dynamics.** $u = u_r + (F/G)[\delta_d - b - G(0)u_r]$ with the stable proper inverse of
       `AbstractLinearSystem.inverse` ($F = (\omega_f/(s+\omega_f))^r$, exact for $r = 0$), run on the reference
       linearly interpolated between its samples (`hold="foh"`). With `preview` (default) the reference is read
       $\tau = r/\omega_f$ ahead (plus $dt/2$ for `hold="zoh"`, the mean lag of a held drive): the low-pass then
       delays nothing below $\omega_f$ to first order, and the last sample is held past the end. Without dynamics,
       $u = \delta_d - b$.
    2. **Creep.** Every creep block is linear and time-invariant, so its sampled response is a causal convolution
       $\mathcal{C}[x] = c * x$ with the kernel $c$ of an impulse; a lower-triangular Toeplitz system is solved
       exactly in O(N log N) (Newton's iteration on power series, FFT). Series ($u = \mathcal{C}[h]$, creep settled
       at $h_r$): $h = h_r + x$ with $x \leftarrow x + c^{-1} * (w - \mathcal{C}[x])$, $w = u - \mathcal{C}_\infty
       h_r$ (`settled_gain()`), from $x = c^{-1} * w$ (exact for `hold="zoh"`; `"foh"` treats its first sample
       differently, which the next steps correct). Parallel ($u = \mathcal{H}[V] + \mathcal{C}[V]$): in $h =
       \mathcal{H}[V]$, $h + \mathcal{C}[\mathcal{H}^{-1}[h]] = u$ by the Newton-like step $h \leftarrow h - (\delta
       + c/s)^{-1} * (h + \mathcal{C}[\mathcal{H}^{-1}[h]] - u)$, $s$ the chord slope of $\mathcal{H}$, from $h = u$:
       a small creep converges like the plain iteration $V \leftarrow \mathcal{H}^{-1}[u - \mathcal{C}[V]]$ (by the
       creep's gain over the hysteresis' slope), a large one by the spread of the hysteresis' slopes about $s$.
       `iterations` steps (a fixed count: reverse-mode differentiable); if the last one still moves the result by
       more than 1e-6 of its size, the call fails (`eqx.error_if`) rather than return it: raise `iterations`.
    3. **Hysteresis.** $V = \mathcal{H}^{-1}[h]$ with `hysteresis.inverse(lower, upper)` from the actuator's initial
       hysteresis state: the analytic PI inverse (without bounds), else per-sample root finding (`HysteresisInverse`,
       saturating at `lower`/`upper`). Without hysteresis, $V = h$, clipped to the bounds if given.

    So `actuator.simulate(inv(delta_d, dt), dt)` tracks $F[\delta_d]$ advanced by the preview: exact at low
    frequency, with the low-pass's error $O((\omega/\omega_f)^2)$ at frequency $\omega$ and the sampling error of the
    held drive. Works under `jit`, `vmap` (equal-length references) and differentiation with respect to the
    reference and the actuator's parameters (`Actuator.inverse` needs `bandwidth` and `relative_degree` given when
    itself called under `jit`).

    **Fields:** `actuator`, `hysteresis_inverse` (or `None`), `hysteresis_state` (its initial state, or `None` for
    its own `init()`), `dynamics_inverse` (or `None`), `delay` [s], `lower`, `upper`, `iterations`, `preview`.
    """

    actuator: eqx.Module  # a `pj.Actuator` (not imported: `Actuator.inverse` builds this, from `_actuator.py`)
    hysteresis_inverse: AbstractHysteresis | None
    hysteresis_state: PyTree[Array] | None
    dynamics_inverse: AbstractLinearSystem | None
    delay: Array
    lower: Array | None
    upper: Array | None
    iterations: int = eqx.field(static=True)
    preview: bool = eqx.field(static=True)

    def __call__(self, displacement: SignalLike, dt: ArrayLike, hold: str = "zoh") -> Signal:
        """The voltage samples for the desired `displacement` [m] (1-D, real, finite), sample step `dt` [s] and the
        `hold` the actuator will be simulated (or driven) with. **Returns:** voltage [V], the shape of
        `displacement`. An actuator's input `delay` is undone by reading the voltage that much ahead (its monotone
        interpolant, so within the drive range; the last sample held, so the last `delay` of the record is not
        compensated; a fractional delay smooths the voltage slightly, read between samples twice)."""
        if hold not in ("zoh", "foh"):
            raise PiezojaxValueError(f'`hold` must be "zoh" or "foh", got {hold!r}')
        dtype = module_float_dtype(self, displacement, dt)
        target = check_signal(displacement, "displacement", dtype)
        dt = check_step(dt, "dt", dtype)
        m = cast_module(self, dtype)
        v = m._voltage(target, dt, hold)
        if m.actuator.delay is None:
            return v
        ahead = check_positive(m.actuator.delay.time, "delay.time", allow_zero=True) / dt
        return m._clip(delay_signal(v[::-1], ahead)[::-1])

    def _voltage(self, target: Array, dt: Array, hold: str) -> Array:
        m, dtype = self, target.dtype
        act = m.actuator.check()
        _, h_r = act._initial(dtype)
        parallel = act.structure == "parallel"
        creep = act.creep
        u_r = h_r if creep is None or parallel else creep.settled_gain() * h_r
        target = target - act.offset
        if act.dynamics is not None:
            if m.preview:
                lead = m.delay + (0.5 * dt if hold == "zoh" else 0.0)
                t = dt * jnp.arange(target.shape[0], dtype=dtype)
                target = jnp.interp(t + lead, t, target)
            u = u_r + m.dynamics_inverse.simulate(target - act.dynamics.dc_gain() * u_r, dt, hold="foh")
        else:
            u = target
        if creep is None:
            return m._invert_hysteresis(u)
        # the creep's sampled response is a causal convolution: its kernel, from an impulse at sample 1 (for "foh"
        # the first sample is special)
        n = u.shape[0]
        kernel = creep.simulate(jnp.zeros(n + 1, dtype).at[1].set(1.0), dt, hold=hold)[1:]
        if not parallel:
            w = u - creep.settled_gain() * h_r
            solve = _toeplitz_inverse(kernel)

            def series(x):
                return x + causal_convolution(w - creep.simulate(x, dt, hold=hold), solve)

            x = _fixed_point(series, causal_convolution(w, solve), m.iterations, "series")
            return m._invert_hysteresis(h_r + x)

        # parallel: H[V] + C[V] = u in the hysteresis output h = H[V]: h + C[H^-1[h]] = u, by Newton-like steps
        # with H^-1 linearised as h / s (s: the chord slope of H over the creep-free inverse),
        # h <- h - (I + C / s)^-1 (h + C[H^-1[h]] - u)
        v0 = m._invert_hysteresis(u)
        slope = jax.lax.stop_gradient(_chord_slope(u, v0, h_r))
        solve = _toeplitz_inverse((kernel / slope).at[0].add(1.0))

        def parallel(h):
            return h - causal_convolution(h + creep.simulate(m._invert_hysteresis(h), dt, hold=hold) - u, solve)

        return m._invert_hysteresis(_fixed_point(parallel, u, m.iterations, "parallel"))

    def _clip(self, v: Array) -> Array:
        return v if self.lower is None else jnp.clip(v, self.lower, self.upper)

    def _invert_hysteresis(self, h: Array) -> Array:
        if self.hysteresis_inverse is None:
            return self._clip(h)
        return self.hysteresis_inverse.scan(h, self.hysteresis_state)[1]


def _chord_slope(u: Array, v: Array, h_rest: Array) -> Array:
    """The chord slope of the hysteresis over the samples $(v_k, u_k)$: their output range over their voltage range;
    for a constant reference (no range) the chord from the rest point $(0, h_{rest})$ to them; 1 where neither has
    one (the reference is the rest output, which the iteration keeps as it is)."""
    tiny = jnp.finfo(u.dtype).tiny
    du, dv = jnp.ptp(u), jnp.ptp(v)
    du_rest, dv_rest = jnp.max(jnp.abs(u - h_rest)), jnp.max(jnp.abs(v))
    return jnp.where((du > 0) & (dv > 0), du / jnp.maximum(dv, tiny),
                     jnp.where((du_rest > 0) & (dv_rest > 0), du_rest / jnp.maximum(dv_rest, tiny), 1.0))


def _toeplitz_inverse(kernel: Array) -> Array:
    r"""The kernel $b$ with `causal_convolution(causal_convolution(x, kernel), b) == x`: the first column of the
    inverse of the lower-triangular Toeplitz matrix of `kernel` (`kernel[0]` != 0), by Newton's iteration on power
    series ($b \leftarrow b(2 - a b)$, doubling the exact length each time; O(N log N) by FFT)."""
    n = kernel.shape[0]
    b = jnp.zeros_like(kernel).at[0].set(1 / kernel[0])
    length = 1
    while length < n:
        length = min(2 * length, n)
        ab = causal_convolution(kernel[:length], b[:length])
        b = b.at[:length].set(2 * b[:length] - causal_convolution(b[:length], ab))
    return b


def _fixed_point(update, x0: Array, iterations: int, structure: str) -> Array:
    """`iterations` steps of `x <- update(x)` from `x0` (a scan: reverse-mode differentiable), then a check that the
    last step moved `x` by at most 1e-6 of its largest value (`eqx.error_if` otherwise: a diverging iteration is
    refused, never returned)."""
    if iterations == 0:
        return x0
    def step(x, _):
        # a diverging iteration keeps its last finite iterate, so that the check below names the iteration (the
        # next update's own input checks would otherwise stop it at a NaN)
        new = update(x)
        return jnp.where(jnp.all(jnp.isfinite(new)), new, x), None

    x_prev = jax.lax.scan(step, x0, None, length=iterations - 1)[0]
    x = update(x_prev)
    moved = jnp.max(jnp.abs(x - x_prev))
    scale = jnp.max(jnp.abs(x))
    ok = jnp.isfinite(moved) & (moved <= 1e-6 * scale)
    return eqx.error_if(
        x, ~jax.lax.stop_gradient(ok),
        f"the {structure} creep's fixed-point iteration did not converge: raise `iterations`, or the creep's gain "
        "exceeds what this iteration inverts (see `ActuatorInverse`)",
    )


def actuator_inverse(
    actuator: eqx.Module,
    lower: ArrayLike | None,
    upper: ArrayLike | None,
    bandwidth: ArrayLike | None,
    relative_degree: int | None,
    iterations: int,
    preview: bool,
    max_iterations: int,
) -> ActuatorInverse:
    """Build the `ActuatorInverse` of `actuator` (see `Actuator.inverse`)."""
    if (lower is None) != (upper is None):
        raise PiezojaxValueError("give both `lower` and `upper` (the admissible voltage range), or neither")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise PiezojaxValueError(f"`iterations` must be an int >= 0, got {iterations!r}")
    if not isinstance(preview, bool):
        raise PiezojaxValueError(f"`preview` must be True or False, got {preview!r}")
    dtype = module_float_dtype(actuator)
    act = cast_module(actuator, dtype).check()
    if lower is not None:
        lower, upper = (jnp.asarray(x, dtype) for x in (lower, upper))
    hyst = act.hysteresis
    h_inv, h_state = None, None
    if hyst is not None:
        h_inv = hyst.inverse(lower, upper, max_iterations=max_iterations)
        state, _ = act._initial(dtype)
        if isinstance(h_inv, HysteresisInverse):
            h_state = None if state is None else (state, jnp.zeros((), dtype))
        elif act.hysteresis_state is not None:
            raise PiezojaxValueError(
                "an actuator with a `hysteresis_state` needs `lower` and `upper`: the analytic inverse starts "
                "demagnetised, the root-finding one from any state"
            )
        elif act.prehistory is not None:
            # the inverse driven by the forward outputs of the excursion 0 -> u_p -> 0 ends in the matching state
            path = jnp.stack([act.prehistory, jnp.zeros((), dtype)])
            h_state = h_inv.scan(hyst(path))[0]
    if act.creep is not None and act.structure == "series":
        c0 = concrete_or_none(act.creep.instantaneous_gain())
        if c0 is not None and not c0 > 0:
            raise PiezojaxValueError(
                "the series creep must have an instantaneous gain > 0 (a DC-normalised creep) to be inverted, "
                f"got {float(c0)}"
            )
    g_inv, delay = None, jnp.zeros((), dtype)
    if act.dynamics is not None:
        # degree and bandwidth resolved once, here: the delay of the low-pass is r / bandwidth
        r = act.dynamics.relative_degree() if relative_degree is None else relative_degree
        if r > 0 and bandwidth is None:
            bandwidth = default_inverse_bandwidth(act.dynamics)
        g_inv = act.dynamics.inverse(bandwidth, r)
        if r > 0:
            delay = r / jnp.asarray(bandwidth, dtype)
    return ActuatorInverse(act, h_inv, h_state, g_inv, delay, lower, upper, iterations, preview)
