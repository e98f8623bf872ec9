"""Exact discretisation of a continuous-time SISO state-space system (ZOH / FOH) and its simulation by `lax.scan`."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    as_float_array,
    check_finite,
    check_signal,
    check_step,
    check_value,
    check_vector,
)
from .._config import use_parallel_scan
from .._custom_types import Signal, SignalLike
from .._dtypes import common_float_dtype, matmul
from .._scans import matrix_affine_scan

_HOLDS = ("zoh", "foh")

# Squarings of the scaling-and-squaring expm: enough for ||M||_1 up to 2**48 (`jax.scipy.linalg.expm`'s default, 16,
# returns NaN above ~3.5e5, e.g. a stiff pole with a long step). Unneeded squarings are masked out.
_MAX_SQUARINGS = 48
_TAYLOR_DEGREE = 18


def expm(M: Float[Array, "k k"]) -> Float[Array, "k k"]:
    r"""Matrix exponential by scaling and squaring with a degree-18 Taylor polynomial; differentiable in both modes.

    $M$ is scaled by $2^{-s}$ to $\|M\|_1 \le 1$, where the truncation error of the Taylor polynomial is below
    $1/19! \approx 8\cdot10^{-18}$ (double precision); the result is squared $s$ times.

    Why not `jax.scipy.linalg.expm` (Padé): it compiles five Padé branches under `lax.cond` plus an LU solve, which
    cost 2-6 s of XLA compile time per matrix shape on our CPU, and every model structure is a new shape; this
    polynomial (Horner, 18 small matmuls) compiles in a fraction of that, needs no solve, and keeps the blocks of
    integrals of $e^{A\tau}$ accurate to relative rounding.
    """
    dtype = M.dtype
    norm = jnp.max(jnp.sum(jnp.abs(M), axis=0))
    # The number of squarings is piecewise constant in M: no gradient flows through it.
    s = jax.lax.stop_gradient(jnp.maximum(jnp.ceil(jnp.log2(norm)), 0.0))
    s = jnp.where(jnp.isfinite(s), s, 0.0)
    X = M / jnp.exp2(s).astype(dtype)
    eye = jnp.eye(M.shape[0], dtype=dtype)

    # Horner: R <- I + X R / k for k = 18..1. Loops keep one matmul each in the compiled graph: XLA:CPU compile
    # time grows with the number of dot ops (18 unrolled ones took ~3 s to compile here).
    def horner(i, R):
        return eye + matmul(X, R) / (_TAYLOR_DEGREE - i).astype(dtype)

    R = jax.lax.fori_loop(0, _TAYLOR_DEGREE, horner, eye)

    def square(i, R):
        return jnp.where(i < s, matmul(R, R), R)

    return jax.lax.fori_loop(0, _MAX_SQUARINGS, square, R)


def check_hold(hold: str) -> str:
    if hold not in _HOLDS:
        raise PiezojaxValueError(f"`hold` must be one of {_HOLDS}, got {hold!r}")
    return hold


def time_step(t: SignalLike, rtol: float = 1e-6) -> Array:
    r"""The sampling step of a uniform, increasing time vector `t`: $dt = (t_{N-1} - t_0)/(N-1)$.

    Checks (with `eqx.error_if`, so also under `jit`) that `t` is finite, strictly increasing and uniform:
    $|t_{k+1} - t_k - dt| \le \mathrm{rtol}\cdot dt$.

    **Arguments:**

    - `t`: sample times, shape `(time,)`, at least 2 samples.
    - `rtol`: tolerance on the step uniformity, relative to `dt`.

    **Returns:** the scalar step `dt`.

    ```python
    dt = pj.time_step(jnp.arange(1000) * 1e-4)   # 1e-4
    ```
    """
    t = check_signal(t, "t")
    if t.shape[0] < 2:
        raise PiezojaxValueError("`t` needs at least 2 samples to define a sampling step")
    t = check_value(t, lambda x: jnp.all(jnp.diff(x) > 0), "`t` must be strictly increasing")
    def uniform(x):
        d = (x[-1] - x[0]) / (x.shape[0] - 1)
        return jnp.all(jnp.abs(jnp.diff(x) - d) <= rtol * d)

    # the step comes from the checked `t`, so that a traced check stays attached to the result
    t = check_value(t, uniform, "`t` must be uniformly sampled")
    return (t[-1] - t[0]) / (t.shape[0] - 1)


class DiscreteStateSpace(eqx.Module):
    r"""An exactly discretised SISO system, in the convention of `scipy.signal.cont2discrete`.

    $\xi_{k+1} = A_d \xi_k + B_d u_k$, $\quad y_k = C_d \xi_k + D_d u_k$.

    For `hold="zoh"` the state is the continuous state, $\xi_k = x(t_k)$. For `hold="foh"` (input linear between
    samples) it is $\xi_k = x(t_k) - \Gamma_1 u_k$, which removes the dependence of the update on $u_{k+1}$; the
    matrices then equal scipy's `cont2discrete(..., method="foh")` and the output equals `scipy.signal.lsim` (default
    linear interpolation).

    **Fields:** `Ad (n, n)`, `Bd (n,)`, `Cd (n,)`, `Dd ()`; `delta = Ad - I` computed without cancellation (the
    update is applied as $\xi + (\delta\,\xi + B_d u)$, which keeps slow poles, $A_d \approx 1 - 10^{-8}$, exact);
    `gamma1 (n,)` the FOH state shift $\Gamma_1$ (zeros for ZOH); `dt`; `hold` (static).

    Build it with `AbstractLinearSystem.discretise` or `discretise_state_space`; the constructor checks the shapes,
    that every matrix is real and finite, and that `dt` is a finite step > 0 (`PiezojaxValueError` naming the field,
    or `eqx.error_if` under `jit`).
    """

    Ad: Float[Array, "n n"]
    Bd: Float[Array, " n"]
    Cd: Float[Array, " n"]
    Dd: Float[Array, ""]
    delta: Float[Array, "n n"]
    gamma1: Float[Array, " n"]
    dt: Float[Array, ""]
    hold: str = eqx.field(static=True)

    def __init__(self, Ad, Bd, Cd, Dd, delta, gamma1, dt, hold: str):
        self.hold = check_hold(hold)
        fields = dict(Ad=Ad, Bd=Bd, Cd=Cd, Dd=Dd, delta=delta, gamma1=gamma1)
        dtype = common_float_dtype(*fields.values())
        arrays = {name: as_float_array(x, name, dtype) for name, x in fields.items()}
        n = arrays["Ad"].shape[0] if arrays["Ad"].ndim == 2 else -1
        shapes = dict(Ad=(n, n), Bd=(n,), Cd=(n,), Dd=(), delta=(n, n), gamma1=(n,))
        for name, shape in shapes.items():
            if arrays[name].shape != shape:
                raise PiezojaxValueError(f"`{name}` must have shape {shape}, got {tuple(arrays[name].shape)}")
        # one check for all the matrices (one `branched_error_if` when traced: this runs at every discretisation)
        checked = check_value(
            tuple(arrays.values()),
            lambda xs: jnp.stack([jnp.all(jnp.isfinite(x)) for x in xs]),
            [f"`{name}` contains NaN or infinite values" for name in arrays],
        )
        self.Ad, self.Bd, self.Cd, self.Dd, self.delta, self.gamma1 = checked
        self.dt = check_step(dt, "dt", dtype)

    @property
    def order(self) -> int:
        return self.Ad.shape[0]

    def init_state(self, x0: ArrayLike | None, u0: ArrayLike) -> Float[Array, " n"]:
        """The discrete state $\\xi_0$ for a continuous state `x0` at the first sample, whose input is `u0`."""
        dtype = self.Ad.dtype
        n = self.order
        if x0 is None:
            x0 = jnp.zeros((n,), dtype)
        else:
            x0 = check_vector(x0, "x0", dtype, allow_empty=True)
            if x0.shape != (n,):
                raise PiezojaxValueError(f"`x0` must have shape ({n},) (the system order), got {tuple(x0.shape)}")
        return x0 - self.gamma1 * jnp.asarray(u0, dtype)

    def scan(self, u: SignalLike, state: ArrayLike | None = None) -> tuple[Float[Array, " n"], Signal]:
        r"""Run the recursion over the input samples `u` from the discrete state `state` (default zeros).

        **Arguments:**

        - `u`: input samples, shape `(time,)`.
        - `state`: discrete state $\xi_0$, shape `(n,)`; default: at rest, `init_state(None, u[0])`. Pass the
          returned state to continue a long record in chunks (exactly, for both holds).

        **Returns:** `(state_N, y)`, the state after the last sample and the output, shape `(time,)`.
        """
        dtype = self.Ad.dtype
        u = check_signal(u, "u", dtype)
        n = self.order
        if state is None:
            state = self.init_state(None, u[0])
        else:
            state = check_vector(state, "state", dtype, allow_empty=True)
            if state.shape != (n,):
                raise PiezojaxValueError(f"`state` must have shape ({n},), got {tuple(state.shape)}")
        if n == 0:
            return state, self.Dd * u
        delta, Bd, Cd, Dd = self.delta, self.Bd, self.Cd, self.Dd

        if use_parallel_scan(u.shape[0]):
            return _scan_parallel(delta, Bd, Cd, Dd, state, u)
        # unroll=1: fastest for small carries on XLA:CPU (measured in _hysteresis/base.py for the same scan shape).
        return jax.lax.scan(lambda xi, uk: self.step(xi, uk), state, u)

    def step(self, xi: Array, uk: Array) -> tuple[Array, Array]:
        r"""One sample without checks: `(xi_next, y_k)`, $y_k = C_d \xi_k + D_d u_k$ and
        $\xi_{k+1} = \xi_k + (\Delta \xi_k + B_d u_k)$ (the body of `scan` and of `pj.Actuator`'s one-loop pass)."""
        # Elementwise products and sums, not `dot`: under jacfwd XLA:CPU runs a batched dot_general inside a scan
        # ~40x slower than the same arithmetic written elementwise (measured in experiments.bench_dynamics).
        y = jnp.sum(self.Cd * xi) + self.Dd * uk
        return xi + (jnp.sum(self.delta * xi[None, :], axis=1) + self.Bd * uk), y

    def simulate(self, u: SignalLike, state: ArrayLike | None = None) -> Signal:
        """The output for input samples `u` from the discrete state `state` (default zeros); see `scan`."""
        return self.scan(u, state)[1]


@jax.custom_jvp
def _scan_parallel(delta, Bd, Cd, Dd, state, u):
    r"""`DiscreteStateSpace.scan` in parallel in time (`matrix_affine_scan`): `(state_N, y)`.

    Derivatives by forward sensitivities: $\dot\xi_{k+1} = A_d\dot\xi_k + \dot\Delta\,\xi_k + \dot B_d u_k
    + B_d\dot u_k$ is the same recurrence with another input, so every tangent direction shares the primal's
    transition (under `jax.jacfwd` only the inputs are batched, not $A_d$'s tangents at every sample)."""
    states, last = matrix_affine_scan(delta, Bd[None] * u[:, None], state)
    return last, matmul(states, Cd) + Dd * u


@functools.partial(_scan_parallel.defjvp, symbolic_zeros=True)
def _scan_parallel_jvp(primals, tangents):
    delta, Bd, Cd, Dd, state, u = primals
    d_delta, dBd, dCd, dDd, dstate, du = (None if type(t) is jax.custom_derivatives.SymbolicZero else t
                                          for t in tangents)
    states, last = matrix_affine_scan(delta, Bd[None] * u[:, None], state)
    y = matmul(states, Cd) + Dd * u
    drive = jnp.zeros_like(states)
    if d_delta is not None:
        drive = drive + matmul(states, d_delta.T)
    if dBd is not None:
        drive = drive + dBd[None] * u[:, None]
    if du is not None:
        drive = drive + Bd[None] * du[:, None]
    dstates, dlast = matrix_affine_scan(delta, drive, jnp.zeros_like(state) if dstate is None else dstate)
    dy = matmul(dstates, Cd)
    if dCd is not None:
        dy = dy + matmul(states, dCd)
    if dDd is not None:
        dy = dy + dDd * u
    if du is not None:
        dy = dy + Dd * du
    return (last, y), (dlast, dy)


def discretise_state_space(
    A: Float[ArrayLike, "n n"],
    B: Float[ArrayLike, " n"],
    C: Float[ArrayLike, " n"],
    D: Float[ArrayLike, ""],
    dt: ArrayLike,
    hold: str = "zoh",
) -> DiscreteStateSpace:
    r"""Exact discretisation of $\dot x = Ax + Bu$, $y = Cx + Du$ for a sampled input held by `hold`.

    With $F = \exp\left(\begin{bmatrix} A\,dt & I & 0 \\ 0 & 0 & I \\ 0 & 0 & 0\end{bmatrix}\right)$,
    $F_{12} = dt\,F[1,2] = \int_0^{dt} e^{A\sigma} d\sigma$ and
    $F_{13} = dt\,F[1,3] = \int_0^{dt} e^{A(dt-\sigma)}\sigma/dt\, d\sigma$:
    $A_d - I = A F_{12}$; ZOH: $B_d = F_{12}B$; FOH: $\Gamma_1 = F_{13}B$, $B_d = F_{12}B + (A_d - I)\Gamma_1$,
    $D_d = D + C\Gamma_1$.

    $A_d - I$ is formed from the integral $F_{12}$ (accurate to relative rounding for every mode) rather than from
    $e^{A dt} - I$, which cancels catastrophically for slow poles ($|p|\,dt \sim 10^{-8}$).

    **Arguments:**

    - `A, B, C, D`: continuous-time realisation, shapes `(n, n)`, `(n,)`, `(n,)`, `()`.
    - `dt`: sampling step (> 0).
    - `hold`: `"zoh"` (input constant between samples) or `"foh"` (linear between samples).

    **Returns:** a `DiscreteStateSpace`.

    ```python
    d = pj.discretise_state_space(-jnp.eye(1), jnp.ones(1), jnp.ones(1), 0.0, 0.1)
    d.Ad  # [[exp(-0.1)]]
    ```
    """
    check_hold(hold)
    A, B, C, D = check_realisation(A, B, C, D)
    dtype = A.dtype
    dt = check_step(dt, "dt", dtype)
    n = A.shape[0]
    eye = jnp.eye(n, dtype=dtype)
    zero = jnp.zeros((n, n), dtype)
    if n == 0:
        empty = jnp.zeros((0,), dtype)
        return DiscreteStateSpace(A, empty, empty, D, A, empty, dt, hold)
    if hold == "zoh":
        M = jnp.block([[A * dt, eye], [zero, zero]])
        F = expm(M)
        F12 = F[:n, n:] * dt
        delta = matmul(A, F12)
        Bd = matmul(F12, B)
        gamma1 = jnp.zeros((n,), dtype)
        Dd = D
    else:
        M = jnp.block([[A * dt, eye, zero], [zero, zero, eye], [zero, zero, zero]])
        F = expm(M)
        F12 = F[:n, n : 2 * n] * dt
        F13 = F[:n, 2 * n :] * dt
        delta = matmul(A, F12)
        gamma1 = matmul(F13, B)
        Bd = matmul(F12, B) + matmul(delta, gamma1)
        Dd = D + matmul(C, gamma1)
    return DiscreteStateSpace(eye + delta, Bd, C, Dd, delta, gamma1, dt, hold)


def check_realisation(A, B, C, D) -> tuple[Array, Array, Array, Array]:
    """Validate shapes of a SISO realisation, cast it to a common float dtype, check it is finite."""
    A, B, C, D = (as_float_array(x, name) for x, name in ((A, "A"), (B, "B"), (C, "C"), (D, "D")))
    dtype = common_float_dtype(A, B, C, D)
    A = as_float_array(A, "A", dtype)
    B = as_float_array(B, "B", dtype)
    C = as_float_array(C, "C", dtype)
    D = as_float_array(D, "D", dtype)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise PiezojaxValueError(f"`A` must be a square (n, n) matrix, got shape {tuple(A.shape)}")
    n = A.shape[0]
    # scipy's (n, 1), (1, n), (1, 1) single-input single-output shapes are accepted too
    B = B[:, 0] if B.shape == (n, 1) else B
    C = C[0] if C.shape == (1, n) else C
    D = D.reshape(()) if D.shape in ((1,), (1, 1)) else D
    if B.shape != (n,):
        raise PiezojaxValueError(f"`B` must have shape ({n},) to match `A` (single input), got {tuple(B.shape)}")
    if C.shape != (n,):
        raise PiezojaxValueError(f"`C` must have shape ({n},) to match `A` (single output), got {tuple(C.shape)}")
    if D.shape != ():
        raise PiezojaxValueError(f"`D` must be a scalar (single input, single output), got shape {tuple(D.shape)}")
    out = [check_finite(x, name) for name, x in (("A", A), ("B", B), ("C", C), ("D", D))]
    return tuple(out)
