r"""Sampled inputs as continuous-time signals (the hold), and the shared diffrax path for input-driven ODEs.

A sampled input is turned into a piecewise-cubic polynomial on a uniform grid of knots:

- `"zoh"`: zero-order hold, $u(t) = u_k$ on $[t_k, t_{k+1})$ (jumps at the samples);
- `"linear"`: first-order hold / linear interpolation between samples (what `scipy.signal.lsim` assumes);
- `"periodic"`: band-limited periodic (trigonometric) interpolation, the record being one period; this is how a
  multisine is defined in continuous time. Evaluated exactly (by FFT) at `upsample` points per sample together with
  its exact derivative, and joined by cubic Hermite pieces in between (relative error about $(\omega h)^4/384$ for a
  component of angular frequency $\omega$ and knot spacing $h$: below 1e-7 for $\omega h < 0.08$).
"""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._checks import (
    PiezojaxValueError,
    as_float_array,
    check_finite,
    check_step,
    check_value,
    nan_where,
    refusing_as_nan,
)
from .._dtypes import common_float_dtype

HOLDS = ("zoh", "linear", "periodic")


def check_samples(u: ArrayLike, name: str, dtype=None) -> Array:
    """Validate sampled input(s): real, shape `(time,)` or `(time, channels)`, non-empty, finite."""
    arr = as_float_array(u, name, dtype)
    if arr.ndim not in (1, 2):
        raise PiezojaxValueError(
            f"`{name}` must have shape (time,) or (time, channels), got shape {tuple(arr.shape)}; "
            "use jax.vmap for a batch of records"
        )
    if arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return check_finite(arr, name)


class SampledInput(eqx.Module):
    r"""A sampled signal held between samples: a piecewise cubic $u(t) = \sum_{j=0}^3 a_{kj}(t - \tau_k)^j$ on knots
    $\tau_k$.

    Build it with `SampledInput.from_samples(u, dt, hold=...)`; evaluate with `u_t = inp.evaluate(t)`.

    **Arguments:**

    - `knots`: finite, strictly increasing knot times, shape `(K + 1,)`, $K \ge 1$.
    - `coeffs`: finite polynomial coefficients in $t - \tau_k$, shape `(K, 4, *channels)`.
    - `hold`: the hold that made it (`"zoh"`, `"linear"` or `"periodic"`).

    Outside $[\tau_0, \tau_K]$ the first / last piece is extended (`"periodic"`: the signal repeats).

    ```python
    inp = SampledInput.from_samples(jnp.array([0.0, 1.0, 0.0]), 0.1, hold="linear")
    inp.evaluate(0.05)  # 0.5
    ```
    """

    knots: Float[Array, " knots"]
    coeffs: Array
    hold: str = eqx.field(static=True)

    def __init__(self, knots: ArrayLike, coeffs: ArrayLike, hold: str):
        if hold not in HOLDS:
            raise PiezojaxValueError(f"`hold` must be one of {HOLDS}, got {hold!r}")
        knots, coeffs = as_float_array(knots, "knots"), as_float_array(coeffs, "coeffs")
        if knots.ndim != 1 or knots.shape[0] < 2:
            raise PiezojaxValueError(f"`knots` must be 1-D with at least 2 entries, got shape {tuple(knots.shape)}")
        if coeffs.ndim < 2 or coeffs.shape[:2] != (knots.shape[0] - 1, 4):
            raise PiezojaxValueError(
                f"`coeffs` must have shape ({knots.shape[0] - 1}, 4, *channels) for {knots.shape[0]} knots, "
                f"got {tuple(coeffs.shape)}"
            )

        def ok(p):
            return jnp.stack([jnp.all(jnp.isfinite(p[0])) & jnp.all(jnp.diff(p[0]) > 0), jnp.all(jnp.isfinite(p[1]))])

        messages = ["`knots` must be finite and strictly increasing", "`coeffs` contains NaN or infinite values"]
        self.knots, self.coeffs = check_value((knots, coeffs), ok, messages)
        self.hold = hold

    @classmethod
    def from_samples(cls, u: ArrayLike, dt: ArrayLike, hold: str = "linear", t0: ArrayLike = 0.0,
                     upsample: int = 8) -> "SampledInput":
        """Hold the samples `u` (shape `(time,)` or `(time, channels)`, taken at `t0 + k dt`) with `hold`.

        `upsample` (only for `hold="periodic"`): knots per sample of the band-limited interpolant.
        """
        if hold not in HOLDS:
            raise PiezojaxValueError(f"`hold` must be one of {HOLDS}, got {hold!r}")
        u = check_samples(u, "u")
        dtype = common_float_dtype(u, dt)
        u = u.astype(dtype)
        dt = check_step(dt, "dt", dtype)
        t0 = check_finite(as_float_array(t0, "t0", dtype), "t0")
        n = u.shape[0]
        zeros = jnp.zeros_like(u)
        if hold == "zoh":
            knots = t0 + dt * jnp.arange(n + 1, dtype=dtype)
            coeffs = jnp.stack([u, zeros, zeros, zeros], axis=1)
        elif hold == "linear":
            if n == 1:
                u2 = jnp.concatenate([u, u])
            else:
                u2 = u
            knots = t0 + dt * jnp.arange(u2.shape[0], dtype=dtype)
            slope = (u2[1:] - u2[:-1]) / dt
            z = jnp.zeros_like(slope)
            coeffs = jnp.stack([u2[:-1], slope, z, z], axis=1)
        else:
            if not isinstance(upsample, int) or upsample < 1:
                raise PiezojaxValueError(f"`upsample` must be a positive int, got {upsample!r}")
            vals, ders = _bandlimited_upsample(u, dt, upsample)
            h = dt / upsample
            m = n * upsample
            knots = t0 + h * jnp.arange(m + 1, dtype=dtype)
            y0, d0 = vals, ders
            y1 = jnp.roll(vals, -1, axis=0)
            d1 = jnp.roll(ders, -1, axis=0)
            a2 = (3.0 * (y1 - y0) / h - 2.0 * d0 - d1) / h
            a3 = (2.0 * (y0 - y1) / h + d0 + d1) / (h * h)
            coeffs = jnp.stack([y0, d0, a2, a3], axis=1)
        return cls(knots=knots, coeffs=coeffs, hold=hold)

    def interval(self, t: ArrayLike) -> Array:
        """Index of the piece that holds time `t` (right-continuous at knots)."""
        k = jnp.searchsorted(self.knots, t, side="right") - 1
        return jnp.clip(k, 0, self.coeffs.shape[0] - 1)

    def evaluate(self, t: ArrayLike) -> Array:
        """The held input at the time `t`, a scalar (the value: a scalar, or a vector of channels); for several times
        use `jax.vmap(input.evaluate)(times)`."""
        if jnp.ndim(t) != 0:
            raise PiezojaxValueError(f"`t` must be a scalar time, got shape {jnp.shape(t)}; for several times use "
                                     "jax.vmap(input.evaluate)(times)")
        if self.hold == "periodic":
            period = self.knots[-1] - self.knots[0]
            t = self.knots[0] + jnp.mod(t - self.knots[0], period)
        k = self.interval(t)
        a = self.coeffs[k]
        tau = (t - self.knots[k]).astype(a.dtype)
        return a[0] + tau * (a[1] + tau * (a[2] + tau * a[3]))


def _bandlimited_upsample(u: Array, dt: Array, factor: int) -> tuple[Array, Array]:
    r"""Values and time derivatives of the periodic trigonometric interpolant of `u` at `factor` points per sample.

    The Nyquist bin (even length) is split evenly between $\\pm$ frequency, i.e. taken as a cosine, so that the
    interpolant is real and passes through every sample.
    """
    n = u.shape[0]
    spec = jnp.fft.rfft(u, axis=0)
    nbins = spec.shape[0]
    if n % 2 == 0 and factor > 1:
        spec = spec.at[-1].multiply(0.5)
    m = n * factor
    full = jnp.zeros((m // 2 + 1,) + spec.shape[1:], dtype=spec.dtype).at[:nbins].set(spec)
    omega = 2.0 * jnp.pi * jnp.arange(m // 2 + 1, dtype=u.dtype) / (n * dt)
    omega = omega.reshape((-1,) + (1,) * (u.ndim - 1))
    vals = jnp.fft.irfft(full, m, axis=0) * factor
    ders = jnp.fft.irfft(full * jax.lax.complex(jnp.zeros_like(omega), omega), m, axis=0) * factor
    return vals.astype(u.dtype), ders.astype(u.dtype)


def simulate_ode(
    vector_field,
    y0: PyTree[Array],
    u: ArrayLike,
    dt: ArrayLike,
    args: PyTree = None,
    *,
    hold: str = "linear",
    substeps: int = 4,
    rtol: float | None = None,
    atol: float | None = None,
    num_samples: int | None = None,
    upsample: int | None = None,
    solver: diffrax.AbstractSolver | None = None,
) -> PyTree[Array]:
    r"""Integrate an input-driven ODE $\dot y = f(t, y, u(t), \text{args})$ with diffrax; save at the sample times.

    The samples `u` are held with `hold` (see `SampledInput`). Default integration: `diffrax.Tsit5` with a
    constant step `dt / substeps` on a grid aligned with the sample times (`diffrax.StepTo`), so that no step
    straddles a jump (`"zoh"`) or a kink (`"linear"`) of the held input. With `rtol` given, a
    `diffrax.PIDController(rtol, atol)` chooses the steps instead (scale the states to O(1) first: its error norm is
    absolute + relative on the raw states). The adjoint is `diffrax.ForwardMode`, so `jax.jacfwd` (and `jax.jvp`)
    work; reverse mode (`jax.grad`) is not supported.

    **Arguments:**

    - `vector_field`: `f(t, y, u_t, args)` returning a pytree like `y`.
    - `y0`: the state at the first sample time `0`.
    - `u`: input samples at `k dt`, shape `(time,)` or `(time, channels)`.
    - `dt`: sample period (> 0).
    - `args`: passed to `vector_field` (e.g. the model).
    - `hold`: `"zoh"`, `"linear"` or `"periodic"`.
    - `substeps`: fixed steps per sample (fixed-step mode) or initial step `dt / substeps` (adaptive mode).
    - `rtol`, `atol`: tolerances of the adaptive mode (`atol` defaults to `rtol`).
    - `num_samples`: how many sample times to save (default all of `u`; fewer is useful with `hold="periodic"`,
      where the whole period defines the interpolant).
    - `upsample`: knots per sample of the periodic interpolant (default `max(substeps, 8)`).
    - `solver`: a diffrax solver (default `diffrax.Tsit5()`).

    **Returns:** the states at `k dt`, `k = 0 .. num_samples - 1`, stacked along a new leading axis. A failed
    integration (the adaptive mode's step budget spent, e.g. on a solution that blows up) raises an
    `eqx.EquinoxRuntimeError`; traced inside `piezojax`'s NaN-refusal mode (as `fitting` traces its residuals) it
    returns NaN states instead, for that member of a `vmap` batch alone. Fixed steps have no step budget: a
    solution that blows up comes back as inf or NaN states, as they are (callers such as a start's candidate scan
    or a plot of a failed fit rely on that; check them where it matters).

    ```python
    f = lambda t, y, u, a: -y + u
    ys = simulate_ode(f, jnp.zeros(()), jnp.ones(100), 0.01, hold="zoh")  # 1 - exp(-t)
    ```
    """
    if not isinstance(substeps, int) or substeps < 1:
        raise PiezojaxValueError(f"`substeps` must be a positive int, got {substeps!r}")
    u = check_samples(u, "u")
    n = u.shape[0]
    if num_samples is None:
        num_samples = n
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or not 1 <= num_samples <= n:
        raise PiezojaxValueError(f"`num_samples` must be an int in [1, len(u)] = [1, {n}], got {num_samples!r}")
    if rtol is not None and (isinstance(rtol, bool) or not isinstance(rtol, (int, float)) or not 0 < rtol < 1):
        raise PiezojaxValueError(f"`rtol` must be a number in (0, 1) or None (fixed steps), got {rtol!r}")
    if atol is not None and (isinstance(atol, bool) or not isinstance(atol, (int, float)) or not 0 <= atol < math.inf):
        raise PiezojaxValueError(f"`atol` must be a finite number >= 0 or None (= `rtol`), got {atol!r}")
    dtype = common_float_dtype(u, dt)
    u = u.astype(dtype)
    dt = check_step(dt, "dt", dtype)
    if upsample is None:
        upsample = max(substeps, 8)
    inp = SampledInput.from_samples(u, dt, hold=hold, upsample=upsample)
    ts = dt * jnp.arange(num_samples, dtype=dtype)
    # With a zero-order hold the integration runs one sample past the last saved time: diffrax merges a step that
    # ends within a few ulp of t1 into t1, which would move the last jump's step boundary onto the jump.
    ts_end = dt * jnp.arange(num_samples + (1 if hold == "zoh" else 0), dtype=dtype)
    t_end = ts_end[-1]
    term = diffrax.ODETerm(lambda t, y, a: vector_field(t, y, inp.evaluate(t), a))
    if solver is None:
        solver = diffrax.Tsit5()
    if num_samples == 1:
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], y0)
    if rtol is None:
        # Fixed steps on a grid aligned with the samples. For a zero-order hold each sample time t_k is preceded by
        # the float just below it, so that every stage of the step ending there sees u_{k-1} (the right-continuous
        # hold gives u_k at t_k itself); the extra step is one ulp long and changes nothing else.
        frac = jnp.arange(substeps, dtype=dtype) / substeps
        grid = ts_end[:-1, None] + dt * frac[None, :]
        if hold == "zoh":
            before = jnp.nextafter(ts_end[1:], jnp.full_like(ts_end[1:], -jnp.inf))
            grid = jnp.concatenate([grid, before[:, None]], axis=1)
        grid = jnp.concatenate([grid.reshape(-1), t_end[None]])
        controller = diffrax.StepTo(ts=grid)
        dt0 = None
        max_steps = grid.shape[0]
    else:
        controller = diffrax.PIDController(rtol=rtol, atol=rtol if atol is None else atol)
        # Steps end exactly at the kinks, and just before / after the jumps, of the held input.
        if hold == "zoh":
            controller = diffrax.ClipStepSizeController(controller, jump_ts=ts_end[1:])
        elif hold == "linear":
            controller = diffrax.ClipStepSizeController(controller, step_ts=ts)
        dt0 = dt / substeps
        max_steps = ts_end.shape[0] * 64 * substeps + 64
    sol = diffrax.diffeqsolve(
        term,
        solver,
        t0=ts[0],
        t1=t_end,
        dt0=dt0,
        y0=y0,
        args=args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        adjoint=diffrax.ForwardMode(),
        max_steps=max_steps,
        # a failed integration (e.g. `max_steps` reached) raises, or under `refusals_as_nan` makes the states NaN
        # (per member of a `vmap` batch, as the value checks do)
        throw=not refusing_as_nan(),
    )
    if refusing_as_nan():
        return nan_where(sol.result != diffrax.RESULTS.successful, sol.ys)
    return sol.ys
