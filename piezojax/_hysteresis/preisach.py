"""The classical Preisach operator: a weighted grid of relays on the half-plane alpha >= beta."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    PiezojaxValueError,
    check_finite,
    check_positive,
    check_scalar,
    check_value,
    check_vector,
    concrete_or_none,
)
from .._custom_types import ScalarLike, VectorLike
from .._dtypes import matmul, param_dtype
from .._parametrisation import setting
from .base import AbstractHysteresis, AbstractHysteresisCell, root_finding_inverse
from .play import (
    _AbstractStopCell,
    check_smoothing,
    error_if_bad_smoothing,
    exact_flag,
    for_every_mapped,
    play_step,
    scan_exact_or_smooth,
    stop_update,
)

_ORDER_MESSAGE = "`alpha` must be >= `beta` for every relay"


def _ordered(p: tuple[Array, Array]) -> Array:
    alpha, beta = p
    return jnp.all(alpha >= beta)


class Preisach(AbstractHysteresisCell):
    r"""The classical Preisach operator, a weighted sum of relays $R_{\alpha_i,\beta_i}$ with
    $\alpha_i \ge \beta_i$.

    $$y = c + \sum_i \mu_i\,R_{\alpha_i,\beta_i}[v],$$

    where the relay $R_{\alpha,\beta}$ switches to $+1$ once $v \ge \alpha$, to $-1$ once $v \le
    \beta$, and otherwise keeps its value. Between samples the input runs along a straight line,
    which is monotone, so checking the end point of each step is exact and the operator is
    rate-independent. A relay with $\alpha = \beta$ that the input reaches exactly takes the value
    of the direction of travel ($+1$ going up, $-1$ going down, unchanged if the input does not
    move).

    The initial (demagnetised) state, input 0, is the staircase $\alpha + \beta = 0$: relays with
    $\alpha + \beta < 0$ are $+1$, those with $\alpha + \beta > 0$ are $-1$, and those on the line
    $\alpha + \beta = 0$ are 0 (half up, half down: the mean of the two ways to demagnetise, and the
    value the play form below gives).

    `smoothing` $s > 0$ gives a smooth relaxation that stays rate-independent. With $r = (\alpha -
    \beta)/2$ and $m = (\alpha + \beta)/2$, $R_{\alpha,\beta}[v] = \mathrm{sign}(P_r[v] - m)$ away
    from ties, with $P_r$ the play operator started at 0. The relaxed operator is $y = c + \sum_i
    \mu_i \tanh\bigl((P^{\varepsilon}_{r_i}[v] - m_i)/\varepsilon\bigr)$, with $\varepsilon = s$ (in
    input units) and $P^{\varepsilon}_r$ the smooth rate-independent play of `play_step` (stop flow
    $dz/dv = \min(1, (r - z)/\varepsilon)$, closed form per step). A static map of rate-independent
    plays is rate-independent, so sampling the same path more finely changes nothing (to rounding).
    The output tends to the exact one as $s \to 0$ at inputs not within $O(\varepsilon)$ of a
    threshold. A good value is half the threshold spacing, $s \approx (v_{\max} - v_{\min})/(2n)$
    for `Preisach.uniform` with $n$ levels. (`smoothing` is a width in input units rather than
    relative to the grid, so that it does not depend on $\max\alpha$, which is not differentiable
    when several relays share it.) Changing `smoothing` does not recompile: both forms are carried
    in the state.

    The state is one array `[v_prev, relays (N), stops (N)]` (relay values, and the stop values $v -
    P_{r_i}$ of the plays, updated by the exact play when $s = 0$ and by the smooth one when $s >
    0$).

    Works under `jit`, `vmap`, `jax.grad` and `jax.jacfwd`; the exact form has zero derivatives
    w.r.t. `alpha`, `beta` and the input (it is piecewise constant in them).

    **Arguments:**

    - `alpha`, `beta`: the switching-up and switching-down inputs of the $N$ relays, 1-D, finite,
      with `alpha >= beta`.
    - `mu`: the weights of the relays, 1-D of length $N$, finite.
    - `offset`: $c$, a finite scalar added to the output, default 0.
    - `smoothing`: $s \ge 0$ (0 = exact), the switching width in input units.

    **Returns:** the operator; called on a signal of shape `(time,)` it returns the output, shape
    `(time,)`.

    ```python
    op = Preisach.uniform(-1.0, 1.0, 10)
    y = op(jnp.sin(jnp.linspace(0, 4 * jnp.pi, 200)))  # shape (200,)
    ```
    """

    alpha: Float[Array, " relays"]
    beta: Float[Array, " relays"]
    mu: Float[Array, " relays"]
    offset: Float[Array, ""]
    smoothing: Float[Array, ""] = setting()

    def __init__(
        self,
        alpha: VectorLike,
        beta: VectorLike,
        mu: VectorLike,
        offset: ScalarLike = 0.0,
        smoothing: ScalarLike = 0.0,
    ):
        dtype = param_dtype(alpha, beta, mu, offset, smoothing)
        alpha = check_vector(alpha, "alpha", dtype)
        beta = check_vector(beta, "beta", dtype)
        self.mu = check_vector(mu, "mu", dtype)
        self.offset = check_scalar(offset, "offset", dtype)
        self.smoothing = check_value(
            check_scalar(smoothing, "smoothing", dtype), lambda s: s >= 0, "`smoothing` must be finite and >= 0"
        )
        n = alpha.shape[0]
        for name, x in (("beta", beta), ("mu", self.mu)):
            if x.shape[0] != n:
                raise PiezojaxValueError(
                    f"`{name}` must have the same length as `alpha` ({n}), got {x.shape[0]}"
                )
        a, b = concrete_or_none(alpha), concrete_or_none(beta)
        if a is not None and b is not None:
            bad = np.nonzero(a < b)[0]
            if bad.size:
                i = int(bad[0])
                raise PiezojaxValueError(
                    f"`alpha` must be >= `beta` for every relay; "
                    f"relay {i} has alpha={a[i]} < beta={b[i]}"
                )
        self.alpha, self.beta = check_value((alpha, beta), _ordered, _ORDER_MESSAGE)

    @classmethod
    def uniform(
        cls,
        v_min: float,
        v_max: float,
        n: int,
        mu: VectorLike | None = None,
        offset: ScalarLike = 0.0,
        smoothing: ScalarLike = 0.0,
    ) -> "Preisach":
        r"""The uniform triangular grid on $v_{\min} \le \beta \le \alpha \le v_{\max}$ with `n`
        levels.

        The square $[v_{\min}, v_{\max}]^2$ is cut into $n \times n$ cells of side $h = (v_{\max} -
        v_{\min})/n$; a relay sits at the centre $(\alpha_i, \beta_j)$ of each cell with $i \ge j$,
        so there are $n(n+1)/2$ relays and those on the diagonal have $\alpha = \beta$. Relays are
        ordered by $\alpha$ index, then $\beta$ index. The centres are placed symmetrically about
        $(v_{\min} + v_{\max})/2$, so a grid symmetric about 0 has relays exactly on $\alpha + \beta
        = 0$.

        **Arguments:**

        - `v_min`, `v_max`: the input range covered, `v_min < v_max` (Python floats: the grid is
          static).
        - `n`: the number of levels, $\ge 1$.
        - `mu`: weights, length $n(n+1)/2$; default $1/(n(n+1)/2)$ each (output in $[-1, 1]$).
        - `offset`, `smoothing`: as for `Preisach`.

        **Returns:** a `Preisach` operator.

        ```python
        op = Preisach.uniform(0.0, 100.0, 20, smoothing=2.5)
        ```
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PiezojaxValueError(f"`n` must be a positive int, got {n!r}")
        v_min, v_max = float(v_min), float(v_max)
        if not (np.isfinite(v_min) and np.isfinite(v_max) and v_min < v_max):
            raise PiezojaxValueError(
                f"`v_min` must be < `v_max` (both finite), got {v_min} and {v_max}"
            )
        h = (v_max - v_min) / n
        centre = 0.5 * (v_min + v_max)
        x = centre + (np.arange(n) - 0.5 * (n - 1)) * h
        i, j = np.tril_indices(n)
        m = i.size
        dtype = param_dtype(*(() if mu is None else (mu,)), offset, smoothing)
        if mu is None:
            mu = np.full(m, 1.0 / m)
        return cls(jnp.asarray(x[i], dtype), jnp.asarray(x[j], dtype), mu, offset, smoothing)

    def check(self) -> "Preisach":
        # One check for all parameters (one `branched_error_if` when traced), outside the scan; it also covers
        # parameters replaced after __init__ (`eqx.tree_at`).
        def ok(p):
            alpha, beta, mu, offset, smoothing = p
            finite = [jnp.all(jnp.isfinite(x)) for x in p]
            return jnp.stack(finite + [_ordered((alpha, beta)), smoothing >= 0])

        messages = [f"`{name}` contains NaN or infinite values" for name in ("alpha", "beta", "mu", "offset")]
        messages += ["`smoothing` must be finite and >= 0", _ORDER_MESSAGE, "`smoothing` must be finite and >= 0"]
        params = check_value((self.alpha, self.beta, self.mu, self.offset, self.smoothing), ok, messages)
        return eqx.tree_at(lambda p: (p.alpha, p.beta, p.mu, p.offset, p.smoothing), self, params)

    @property
    def num_relays(self) -> int:
        return self.alpha.shape[0]

    def init(self) -> Float[Array, " state"]:
        """The demagnetised state with the input at 0: `[0, -sign(alpha + beta), zeros]`."""
        relays = -jnp.sign(self.alpha + self.beta)
        zero = jnp.zeros((1,), relays.dtype)
        return jnp.concatenate([zero, relays, jnp.zeros_like(relays)])

    def relays(self, state: Float[Array, " state"]) -> Float[Array, " relays"]:
        """The relay values (exact form) held in `state`."""
        return state[1 : 1 + self.num_relays]

    def step(
        self, state: Float[Array, " state"], v: Float[ArrayLike, ""]
    ) -> tuple[Float[Array, " state"], Array]:
        """Advance along the straight line from the previous input to `v`; return `(state, y)`."""
        n = self.num_relays
        if jnp.shape(state) != (2 * n + 1,):
            raise PiezojaxValueError(
                f"`state` must have shape ({2 * n + 1},) ([v_prev, relays, stops]), "
                f"got {jnp.shape(state)}"
            )
        v = jnp.asarray(v, state.dtype)
        v_prev, relays, stops = state[0], state[1 : 1 + n], state[1 + n :]
        one = jnp.ones_like(relays)
        up = v >= self.alpha
        down = v <= self.beta
        direction = jnp.where(v > v_prev, one, jnp.where(v < v_prev, -one, relays))
        relays = jnp.where(up & down, direction, jnp.where(up, one, jnp.where(down, -one, relays)))

        half_width = 0.5 * (self.alpha - self.beta)
        delta = v - v_prev
        eps = self.smoothing
        smooth = eps > 0

        def smooth_branch(stops):
            middle = 0.5 * (self.alpha + self.beta)
            eps_s = jnp.where(smooth, eps, jnp.ones_like(eps))
            # play_step takes the smoothing relative to each threshold (width s r); ours is one
            # absolute width.
            pos_r = half_width > 0
            r_s = jnp.where(pos_r, half_width, jnp.ones_like(half_width))
            rel = jnp.where(pos_r, eps / r_s, jnp.zeros_like(half_width))
            stops = play_step(stops, delta, half_width, rel)
            return stops, jnp.sum(self.mu * jnp.tanh((v - stops - middle) / eps_s))

        def exact_branch(stops):
            # The exact plays are only carried in the state (the output comes from the relays), so
            # the tie-splitting derivative of `clip` does not matter here.
            return jnp.clip(stops + delta, -half_width, half_width), jnp.sum(self.mu * relays)

        # A `cond` rather than computing both: skipping the smooth plays halves the cost of the
        # exact form on large grids (measured 4.0 -> 2.3 us per sample for 210 relays). Under `vmap`
        # over stacked operators the outer predicate stays unmapped (`for_every_mapped`: exact for
        # all of them), where a mapped `cond` runs both branches; the inner one then picks per
        # operator (one branch without `vmap`, both under it).
        def smooth_or_exact(stops):
            return jax.lax.cond(smooth, smooth_branch, exact_branch, stops)

        stops, y = jax.lax.cond(for_every_mapped(~smooth), exact_branch, smooth_or_exact, stops)
        y = self.offset + y
        return jnp.concatenate([v[None], relays, stops]), y


class GaussianPreisach(_AbstractStopCell):
    r"""A Preisach operator with a separable Gaussian density, computed exactly in $s$ through its play form.

    With half-width $r = (\alpha - \beta)/2$ and centre $s = (\alpha + \beta)/2$, the relay of the demagnetised
    Preisach operator is $R_{\alpha,\beta}[v] = \mathrm{sign}(P_r[v] - s)$, $P_r$ the play operator started at 0
    (Mayergoyz; Krejčí). For a density $\mu(r, s)$ (per unit $r$ and $s$) that is even in $s$,

    $$\int_0^\infty\!\!\int_{-\infty}^{\infty}\mu\,\mathrm{sign}(P_r[v] - s)\,ds\,dr
      = 2\int_0^\infty\!\!\int_0^{P_r[v]}\mu(r, s)\,ds\,dr,$$

    and for $\mu = c\,e^{-r^2/2\sigma_r^2}e^{-s^2/2\sigma_s^2}$ the inner integral is an error function of the
    play output. With the midpoint rule on $n$ nodes $r_j = (j + \tfrac12)h$, $h = r_{\max}/n$:

    $$y = w_0 v + \sum_j w_j\,\varphi(P_{r_j}[v]),\quad \varphi(p) = \int_0^p e^{-s^2/2\sigma_s^2}ds
      = \sigma_s\sqrt{\pi/2}\,\mathrm{erf}\bigl(p/(\sqrt2\sigma_s)\bigr),\quad
      w_j = 2c\,h\,e^{-r_j^2/2\sigma_r^2}.$$

    A "generalised Prandtl–Ishlinskii" operator with odd, saturating shape $\varphi$ (the PI class has $\varphi(p) =
    p$, reached as $\sigma_s \to \infty$): it is a Preisach operator (density on the lines $r = r_j$, Gaussian in
    $s$), so it has return-point memory, wiping-out and congruent minor loops, which Bouc–Wen lacks. Plays with $r \geq
    \max|v|$ never leave 0, so truncating the $r$ integral at $r_{\max}$ is exact for inputs within $\pm r_{\max}$;
    the midpoint rule in $r$ is the only discretisation (for the `IvanBench` default, $h$ = 1 V, it is within
    8e-3 V of $h$ = 1/8 V on the paper's contact drive, against a 1.6 V loop width). Exact plays by default;
    `smoothing` $> 0$ uses the smooth rate-independent play of `play_step`. Works under `jit`, `vmap`, `jax.grad`
    and `jax.jacfwd`.

    **Arguments:**

    - `density`: $c$ [1/V], the density at the origin (per V of $r$ and per V of $s$).
    - `sigma_r`, `sigma_s` [V]: widths of the density in half-width and centre.
    - `w0`: the reversible linear gain.
    - `r_max` [V], `n`: quadrature range and number of nodes (static).
    - `smoothing`: relative play smoothing $\geq 0$ (array field; 0 = exact, chosen at trace time when concrete).

    **Returns:** called on a signal of shape `(time,)`, the output, shape `(time,)` (in the units of the input).

    ```python
    op = pj.GaussianPreisach(0.005, 100.0, 100.0, w0=0.9)
    y = op(-20.0 * jnp.abs(jnp.sin(jnp.linspace(0, 6, 3000))))
    ```
    """

    w0: Array
    weights: Array
    thresholds: Array
    sigma_s: Array
    smoothing: Array = setting()
    _block: int = eqx.field(static=True, default=1024)

    def __init__(self, density: ArrayLike, sigma_r: ArrayLike, sigma_s: ArrayLike, *, w0: ArrayLike = 1.0,
                 r_max: float = 100.0, n: int = 100, smoothing: float = 0.0):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PiezojaxValueError(f"`n` must be a positive int, got {n!r}")
        if not (np.isfinite(r_max) and r_max > 0):
            raise PiezojaxValueError(f"`r_max` must be finite and > 0, got {r_max!r}")
        dtype = param_dtype(density, sigma_r, sigma_s, w0)
        density, sigma_r = jnp.asarray(density, dtype), jnp.asarray(sigma_r, dtype)
        for name, x in (("density", density), ("sigma_r", sigma_r), ("sigma_s", sigma_s), ("w0", w0)):
            if jnp.ndim(x) != 0:
                raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {jnp.shape(x)}")
        density = check_positive(density, "density", allow_zero=True)
        sigma_r = check_positive(sigma_r, "sigma_r")
        h = float(r_max) / n
        r = jnp.asarray((np.arange(n) + 0.5) * h, dtype)
        self.thresholds = r
        self.weights = 2 * density * h * jnp.exp(-0.5 * (r / sigma_r) ** 2)
        self.sigma_s = jnp.asarray(sigma_s, dtype)
        self.sigma_s = check_positive(self.sigma_s, "sigma_s")
        self.w0 = check_finite(jnp.asarray(w0, dtype), "w0")
        self.smoothing = check_smoothing(smoothing, dtype)

    def check(self) -> "GaussianPreisach":
        sig = check_positive(self.sigma_s, "sigma_s")
        return eqx.tree_at(lambda o: (o.sigma_s, o.weights, o.thresholds, o.smoothing), self,
                           (sig, check_positive(self.weights, "weights", allow_zero=True),
                            check_positive(self.thresholds, "thresholds", allow_zero=True),
                            error_if_bad_smoothing(self.smoothing)))

    def _output(self, v: Array, z: Array) -> Array:
        sig = self.sigma_s
        c = jnp.sqrt(jnp.asarray(0.5, v.dtype))
        phi = sig * jnp.sqrt(jnp.pi / 2).astype(v.dtype) * jax.lax.erf(c * (v[..., None] - z) / sig)
        return self.w0 * v + matmul(phi, self.weights)

    def _run(self, state, signal):
        # The plays run in a tight loop over blocks of samples and the shape function is applied to each block at
        # once: an erf per play per sample inside the loop is 2-3x slower (measured: 1e6 samples, 100 plays).
        # Padding repeats the last sample, which moves no play, so the final state is unchanged.
        t = signal.shape[0]
        b = min(t, self._block)
        pad = (-t) % b
        blocks = jnp.concatenate([signal, jnp.broadcast_to(signal[-1], (pad,))]).reshape(-1, b)

        def run(exact):
            def inner(carry, v):
                v_prev, z = carry
                z = stop_update(z, v - v_prev, self.thresholds, self.smoothing, exact)
                return (v, z), z

            def outer(carry, vb):
                carry, zb = jax.lax.scan(inner, carry, vb)
                return carry, self._output(vb, zb)

            return jax.lax.scan(outer, state, blocks)

        final, y = scan_exact_or_smooth(exact_flag(self.smoothing), self.smoothing, run)
        return final, y.reshape(-1)[:t]

    def inverse(
        self, lower: ScalarLike | None = None, upper: ScalarLike | None = None, *, max_iterations: int = 100
    ) -> AbstractHysteresis:
        return root_finding_inverse(self, lower, upper, max_iterations)
