"""The Bouc–Wen hysteresis operator in its rate-independent increment form."""

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, check_scalar, check_value, concrete_or_none
from .._custom_types import ScalarLike, Signal
from .._dtypes import param_dtype
from .._parametrisation import setting
from .base import AbstractHysteresis, root_finding_inverse

_OUTPUTS = ("dv-z", "dv+z", "z")
_METHODS = ("closed_form", "rk4")
_PARAMS = ("A", "beta", "gamma", "n", "d", "smoothing")
_UNBOUNDED_MESSAGE = (
    "unstable Bouc-Wen parameters (z grows without bound): need `beta` >= 0, and `beta` + `gamma` >= 0 if A > 0, "
    "`beta` - `gamma` >= 0 if A < 0"
)


def _bounded(p: tuple[Array, Array, Array]) -> Array:
    """True if z stays bounded from the relaxed state for every input (the condition in `BoucWen`'s docstring)."""
    A, beta, gamma = p
    return (beta >= 0) & ((A <= 0) | (beta + gamma >= 0)) & ((A >= 0) | (beta - gamma >= 0))


def _phi(x: Array) -> Array:
    """$(e^x - 1)/x$ with its limit 1 at $x = 0$ and accurate derivatives near 0."""
    small = jnp.abs(x) < 1e-2
    xs = jnp.where(small, jnp.ones_like(x), x)
    series = 1 + x * (1 / 2 + x * (1 / 6 + x * (1 / 24 + x / 120)))
    return jnp.where(small, series, jnp.expm1(xs) / xs)


def _psi(x: Array) -> Array:
    """$\\log(1 + x)/x$ with its limit 1 at $x = 0$ (for $x > -1$)."""
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, jnp.ones_like(x), x)
    series = 1 - x * (1 / 2 - x * (1 / 3 - x * (1 / 4 - x / 5)))
    return jnp.where(small, series, jnp.log1p(xs) / xs)


def _affine_flow(w0: Array, u: Array, a: Array, k: Array) -> Array:
    """Exact solution of $dw/du = a - k w$ after $u \\ge 0$, safe for $k \\le 0$ and $k = 0$."""
    return w0 + (a - k * w0) * u * _phi(-k * u)


def _closed_form_flow(w0: Array, u: Array, a: Array, beta: Array, gamma: Array) -> Array:
    """Exact flow of $dw/du = a - \\beta w - \\gamma |w|$ (Bouc–Wen with n = 1) over $u \\ge 0$.

    The right-hand side is affine on each side of $w = 0$: rate $k_+ = \\beta + \\gamma$ for $w \\ge
    0$ and $k_- = \\beta - \\gamma$ for $w < 0$. The trajectory crosses 0 at most once (towards the
    sign of $a$), at $\\tau = \\log(1 - k w_0 / a)/k$, after which it follows the other affine flow
    from 0.
    """
    kp = beta + gamma
    km = beta - gamma
    pos0 = (w0 > 0) | ((w0 == 0) & (a >= 0))
    k0 = jnp.where(pos0, kp, km)
    k1 = jnp.where(pos0, km, kp)
    can_cross = w0 * a < 0
    a_s = jnp.where(can_cross, a, jnp.ones_like(a))
    x = -k0 * w0 / a_s
    reach = can_cross & (
        x > -1
    )  # x <= -1: the orbit runs away from 0 (k0 < 0) and never reaches it
    x_s = jnp.where(reach, x, jnp.zeros_like(x))
    tau = jnp.where(reach, (-w0 / a_s) * _psi(x_s), jnp.full_like(x, jnp.inf))
    cross = tau < u
    u1 = jnp.where(cross, tau, u)
    w1 = jnp.where(cross, jnp.zeros_like(w0), _affine_flow(w0, u1, a, k0))
    u2 = jnp.where(cross, u - jnp.where(cross, tau, jnp.zeros_like(tau)), jnp.zeros_like(u))
    return jnp.where(cross, _affine_flow(w1, u2, a, k1), w1)


def _rhs(w: Array, a: Array, beta: Array, gamma: Array, n: Array, eps: Array) -> Array:
    r"""$f(w) = a - (\beta w + \gamma\rho)\,\rho^{n-1}$, $\rho = \sqrt{w^2 + \varepsilon^2}$ ($|w|$
    if $\varepsilon = 0$).

    The square root and the power only see `where`-guarded arguments (double `where`), so $w = 0$
    with $\varepsilon = 0$ gives $f = a$ and finite gradients (w.r.t. $n$, and w.r.t. $w$ for $n <
    1$; there $\partial f/\partial w$ is taken as $-\beta$, the mean of the one-sided slopes for $n
    = 1$). Written without $w/\rho$ and without `exp(c * log(q))`: on XLA:CPU both forms ran ~10x
    slower than `pow` in this loop.
    """
    q = w * w + eps * eps
    rho_s = jnp.sqrt(jnp.where(q > 0, q, jnp.ones_like(q)))
    rho = jnp.where(eps > 0, rho_s, jnp.abs(w))
    return a - (beta * w + gamma * rho) * rho_s ** (n - 1)


def _rk4_step(w: Array, h: Array, a, beta, gamma, n, eps) -> Array:
    """One classical RK4 step of size `h` for $dw/du = f(w)$."""
    k1 = _rhs(w, a, beta, gamma, n, eps)
    k2 = _rhs(w + 0.5 * h * k1, a, beta, gamma, n, eps)
    k3 = _rhs(w + 0.5 * h * k2, a, beta, gamma, n, eps)
    k4 = _rhs(w + h * k3, a, beta, gamma, n, eps)
    return w + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)


def _rk4_flow(w0, u, a, beta, gamma, n, eps, substeps: int) -> Array:
    """`substeps` RK4 steps of size $u/$`substeps` over $[0, u]$.

    A rolled loop: XLA:CPU fuses an unrolled chain of RK stages into one expression and recomputes
    every shared stage in each consumer, which is exponential in the number of stages (measured: 27
    µs per sample for 8 unrolled sub-steps against 85 ns for one).
    """
    h = u / substeps
    if substeps == 1:
        return _rk4_step(w0, h, a, beta, gamma, n, eps)
    return jax.lax.fori_loop(0, substeps, lambda _, w: _rk4_step(w, h, a, beta, gamma, n, eps), w0)


class BoucWen(AbstractHysteresis):
    r"""The Bouc–Wen hysteresis operator, rate-independent increment form.

    $$dz = A\,dv - \beta\,|dv|\,|z|^{n-1} z - \gamma\,dv\,|z|^n,\qquad y = d\,v - z.$$

    Between two samples the input runs along a straight line, so $\sigma = \mathrm{sign}(dv)$ is
    constant and $z$ solves an ODE *in the input*: with $u = |v - v_{k-1}|$ and $w = \sigma z$,
    $dw/du = f(w) = A - \beta|w|^{n-1}w - \gamma|w|^n$, the same equation for both directions. Each
    step integrates it over the whole increment, so the output does not depend on how finely a
    piecewise-linear input is sampled.

    - `method="closed_form"` ($n = 1$, `smoothing` 0): $f$ is affine on each side of $w = 0$ (rate
      $\beta + \gamma$ above, $\beta - \gamma$ below), so each step is solved exactly, with
      `expm1`/`log1p` formulas that are safe for zero or negative rates; the trajectory crosses $w =
      0$ at most once per step. `n` must be 1 (a `PiezojaxValueError`, under `jit`/`vmap`
      an `EquinoxRuntimeError`, otherwise) and its gradient is zero: use `method="rk4"` to fit `n`.
    - `method="rk4"`: `substeps` classical RK4 steps of size $h = |\Delta v|/$`substeps` per sample,
      any $n > 0$ and any `smoothing`. $f$ is smooth except at $w = 0$, so the error is $O(h^4)$
      while $z$ keeps its sign and larger in the sub-steps where $z$ changes sign (kink of $f$; for
      $n < 1$ an infinite slope). Measured against a DOP853 solution (rtol 1e-13) on a two-period
      sine of amplitude $3z_{\max}/A$ with 60 samples and 8 sub-steps: max error / $z_{\max}$ = 9e-5
      ($n = 1$), 1.3e-4 ($n = 0.7$), 6e-6 ($n = 1.5$, $n = 2$); 16 sub-steps: 1.7e-5, 4.7e-5,
      1.2e-6, 4.9e-7. RK4 is unstable for $h\,n(\beta+|\gamma|)\max|z|^{n-1} > 2.78$ (the stiffness
      of $f$ on either side of 0): raise `substeps` for large input steps.

    **Allowed parameters (bounded $z$).** On the two sides of $w = 0$, $f(w) = A - (\beta+\gamma)w^n$
    ($w \ge 0$) and $f(w) = A + (\beta-\gamma)|w|^n$ ($w < 0$), and a reversal of the input maps $w$
    to $-w$. For $A > 0$, starting from the relaxed state:

    - $\beta + \gamma > 0$ and $\beta \ge 0$: $|z| \le z_{\max} = (A/(\beta+\gamma))^{1/n}$ for every
      input: $f(z_{\max}) = 0$, and for $-z_{\max} \le w < 0$, $f(w) \ge A + (\beta-\gamma)A/(\beta+\gamma)
      = 2\beta A/(\beta+\gamma) \ge 0$. With $\beta \ge |\gamma|$ (the bounded class of Ikhouane &
      Rodellar: $A > 0$, $\beta+\gamma > 0$, $\beta-\gamma \ge 0$) the bound $\max(|z_0|, z_{\max})$
      holds from any initial state; with $\gamma > \beta$ only from $|z_0| \le z_{\max}$ (a state below
      $-(A/(\gamma-\beta))^{1/n}$ runs away).
    - $\beta + \gamma = 0$: no saturation: while $z$ moves with the input it grows linearly, $dw/du = A$,
      and $|z|$ never grows faster than $A$ per unit of input travel (a linear term, no blow-up).
      Allowed.
    - $\beta + \gamma < 0$: a monotone input drives $z$ without bound ($f \ge A$ grows with $w$):
      exponentially in the input travel for $n = 1$ (the closed form's $e^{|\beta+\gamma| u}$), to infinity
      at a finite input travel for $n > 1$. Rejected.
    - $\beta < 0$ (and $\beta + \gamma > 0$): a long monotone input brings $z$ near $z_{\max}$; after a
      reversal $w = -z$ sits where $f < 0$ and runs away. Rejected.

    $A < 0$ is the mirror image ($z \to -z$ swaps $\beta + \gamma$ and $\beta - \gamma$), and $A = 0$ keeps
    $z = 0$ from rest. So the constructor and every call reject (`PiezojaxValueError` for concrete values,
    `eqx.error_if` under `jit`, naming `beta` and `gamma`) unless $\beta \ge 0$, $\beta + \gamma \ge 0$ if
    $A > 0$, and $\beta - \gamma \ge 0$ if $A < 0$; e.g. `BoucWen(1.0, -0.5, 0.01)`, whose closed form grows
    like $e^{0.49\,u}$, is rejected. `BoucWenOscillator` (the benchmark's ODE) does not impose this.

    `smoothing` $s \ge 0$ (rk4 only) replaces $|w|$ by $\rho = \sqrt{w^2 + (s\,z_{\max})^2}$ in $f$,
    i.e. $f_s(w) = A - \beta\rho^{n-1}w - \gamma\rho^n$. This removes the kink of $f$ at $z = 0$
    (and, for $n < 1$, its infinite slope; for any $n$, the $\log|z|$ in $\partial f/\partial n$).
    It is still an ODE in the input, so it stays rate-independent, and it tends to the exact
    operator as $s \to 0$ (error $O(s)$). $z_{\max}$ is replaced by 1 when $A \le 0$ or $\beta +
    \gamma \le 0$. Changing `smoothing` does not recompile.

    The state is the array `[v_prev, z]`; `init(v0, z0)` builds one (default: relaxed, input 0, $z =
    0$). Works under `jit`, `vmap`, `jax.grad` and `jax.jacfwd` (w.r.t. the parameters, the input
    and the state).

    **Arguments:**

    - `A`, `beta`, `gamma`: the Bouc–Wen coefficients (finite scalars; bounded $z$ as above).
    - `n`: the exponent, $n > 0$ (finite scalar), default 1.
    - `d`: the linear coefficient of the output (finite scalar), default 0.
    - `output` (static): `"dv-z"` ($y = d v - z$, default, the usual piezo form), `"dv+z"` ($y = d v
      + z$) or `"z"` ($y = z$).
    - `smoothing`: see above, default 0 (exact).
    - `method` (static): `"closed_form"`, `"rk4"`, or `None`: the closed form if `n` is concretely 1
      and `smoothing` concretely 0, else rk4.
    - `substeps` (static): RK4 steps per sample, default 8.

    **Returns:** the operator; called on a signal of shape `(time,)` it returns the output, shape
    `(time,)`.

    ```python
    op = BoucWen(A=0.8, beta=0.03, gamma=0.01, d=1.0)
    v = 50 * jnp.sin(jnp.linspace(0, 4 * jnp.pi, 400))
    y = op(v)  # shape (400,)
    ```
    """

    A: Float[Array, ""]
    beta: Float[Array, ""]
    gamma: Float[Array, ""]
    n: Float[Array, ""]
    d: Float[Array, ""]
    smoothing: Float[Array, ""] = setting()
    output: str = eqx.field(static=True)
    method: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)

    def __init__(
        self,
        A: ScalarLike,
        beta: ScalarLike,
        gamma: ScalarLike,
        n: ScalarLike = 1.0,
        d: ScalarLike = 0.0,
        *,
        output: Literal["dv-z", "dv+z", "z"] = "dv-z",
        smoothing: ScalarLike = 0.0,
        method: Literal["closed_form", "rk4"] | None = None,
        substeps: int = 8,
    ):
        dtype = param_dtype(A, beta, gamma, n, d, smoothing)
        self.A = check_scalar(A, "A", dtype)
        self.beta = check_scalar(beta, "beta", dtype)
        self.gamma = check_scalar(gamma, "gamma", dtype)
        self.n = check_value(check_scalar(n, "n", dtype), lambda x: x > 0, "`n` must be > 0")
        self.d = check_scalar(d, "d", dtype)
        self.smoothing = check_value(
            check_scalar(smoothing, "smoothing", dtype), lambda x: x >= 0, "`smoothing` must be >= 0 (0 = exact)"
        )
        coeffs = (self.A, self.beta, self.gamma)
        values = [concrete_or_none(x) for x in coeffs]
        got = "" if any(v is None for v in values) else ", got A={}, beta={}, gamma={}".format(*map(float, values))
        self.A, self.beta, self.gamma = check_value(coeffs, _bounded, _UNBOUNDED_MESSAGE + got)
        if output not in _OUTPUTS:
            raise PiezojaxValueError(f"`output` must be one of {_OUTPUTS}, got {output!r}")
        n_val = concrete_or_none(self.n)
        s_val = concrete_or_none(self.smoothing)
        if method is None:
            method = (
                "closed_form"
                if (n_val is not None and n_val == 1 and s_val is not None and s_val == 0)
                else "rk4"
            )
        if method not in _METHODS:
            raise PiezojaxValueError(f"`method` must be one of {_METHODS} or None, got {method!r}")
        if method == "closed_form" and n_val is not None and n_val != 1:
            raise PiezojaxValueError(
                f"`method='closed_form'` needs `n` = 1, got n = {float(n_val)}"
            )
        if method == "closed_form" and s_val is not None and s_val != 0:
            raise PiezojaxValueError(
                "`smoothing` > 0 needs `method='rk4'` (the closed form is the exact operator)"
            )
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise PiezojaxValueError(f"`substeps` must be a positive int, got {substeps!r}")
        self.output = output
        self.method = method
        self.substeps = substeps

    def check(self) -> "BoucWen":
        # One check (one `branched_error_if` when traced) for all parameters, outside the scan: it also covers
        # parameters replaced after __init__ (`eqx.tree_at`, as a fitter does).
        closed_form = self.method == "closed_form"

        def ok(p):
            A, beta, gamma, n, d, s = p
            return jnp.stack(
                [jnp.isfinite(x) for x in p]
                + [n > 0, s >= 0, _bounded((A, beta, gamma))]
                + ([n == 1, s == 0] if closed_form else [])
            )

        messages = [f"`{name}` contains NaN or infinite values" for name in _PARAMS] + [
            "`n` must be > 0",
            "`smoothing` must be >= 0",
            _UNBOUNDED_MESSAGE,
        ]
        if closed_form:
            messages += ["`method='closed_form'` needs `n` = 1", "`smoothing` > 0 needs `method='rk4'`"]
        params = check_value(tuple(getattr(self, name) for name in _PARAMS), ok, messages)
        return eqx.tree_at(lambda m: tuple(getattr(m, name) for name in _PARAMS), self, params)

    zero_at_rest: ClassVar[bool | None] = True

    def init(self, v0: ScalarLike = 0.0, z0: ScalarLike = 0.0) -> Float[Array, "2"]:
        """The state `[v_prev, z]`; by default relaxed ($z = 0$) with the input at 0.

        **Arguments:**

        - `v0`: the input value the next sample starts from.
        - `z0`: the hysteretic variable $z$.

        **Returns:** the state, shape `(2,)`.
        """
        dtype = self.A.dtype
        return jnp.stack([check_scalar(v0, "v0", dtype), check_scalar(z0, "z0", dtype)])

    def z_max(self) -> Float[Array, ""]:
        r"""The bound $(A/(\beta+\gamma))^{1/n}$ on $|z|$ (when $A > 0$, $\beta+\gamma>0$, $\beta \ge 0$,
        from $|z_0| \le z_{\max}$; see the class docstring)."""
        n = self.n if self.method == "rk4" else jnp.ones_like(self.n)
        return (self.A / (self.beta + self.gamma)) ** (1 / n)

    def _flow(self, w0: Array, u: Array, substeps: int) -> Array:
        if self.method == "closed_form":
            return _closed_form_flow(w0, u, self.A, self.beta, self.gamma)
        k = self.beta + self.gamma
        valid = (self.A > 0) & (k > 0)
        ratio = jnp.where(valid, self.A / jnp.where(valid, k, jnp.ones_like(k)), jnp.ones_like(k))
        eps = self.smoothing * ratio ** (1 / self.n)
        return _rk4_flow(w0, u, self.A, self.beta, self.gamma, self.n, eps, substeps)

    def _step(self, state: Array, v: Array, substeps: int) -> tuple[Array, Array]:
        if jnp.shape(state) != (2,):
            raise PiezojaxValueError(
                f"`state` must have shape (2,) ([v_prev, z]), got {jnp.shape(state)}"
            )
        v = jnp.asarray(v, state.dtype)
        v_prev, z = state[0], state[1]
        dv = v - v_prev
        sigma = jnp.where(dv >= 0, jnp.ones_like(dv), -jnp.ones_like(dv))
        u = sigma * dv  # |dv|, with derivative sigma (the right derivative at dv = 0)
        z_new = sigma * self._flow(sigma * z, u, substeps)
        if self.output == "dv-z":
            y = self.d * v - z_new
        elif self.output == "dv+z":
            y = self.d * v + z_new
        else:
            y = z_new
        return jnp.stack([v, z_new]), y

    def step(
        self, state: Float[Array, "2"], v: Float[ArrayLike, ""]
    ) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        """Advance along the straight line from the previous input to `v`; return `(state, y)`."""
        return self._step(state, v, self.substeps)

    def _run(self, state: Array, signal: Signal) -> tuple[Array, Signal]:
        # Same result as scanning `step`. With `method="rk4"` the scan runs one RK4 sub-step per scan iteration over
        # the input with `substeps - 1` points inserted on each straight segment (the same path, so the same
        # sub-steps up to rounding): a rolled sub-step loop inside each scan step costs ~5x more on XLA:CPU. Here,
        # in `_run`, wrappers (`OutputPolynomial`, `ScaledHysteresis`) get it too.
        if state.shape != (2,):
            raise PiezojaxValueError(f"`state` must have shape (2,) ([v_prev, z]), got {state.shape}")
        m = self.substeps
        if self.method != "rk4" or m == 1:
            return jax.lax.scan(lambda c, v: self._step(c, v, m), state, signal, unroll=self._unroll())
        prev = jnp.concatenate([state[:1], signal[:-1]])
        frac = jnp.arange(1, m, dtype=signal.dtype) / m
        inner = prev[:, None] + frac[None, :] * (signal - prev)[:, None]
        fine = jnp.concatenate([inner, signal[:, None]], axis=1).reshape(-1)
        final, y = jax.lax.scan(lambda c, v: self._step(c, v, 1), state, fine, unroll=self._unroll())
        return final, y[m - 1 :: m]

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        return root_finding_inverse(self, lower, upper, max_iterations)
