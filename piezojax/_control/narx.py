"""A NARX model whose nonlinear map is a one-hidden-layer network (paper 002, eq. 10–16)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import PiezojaxValueError, check_scalar_param, check_signal, check_value
from .._custom_types import AbstractCell, Signal, SignalLike
from .._dtypes import cast_module, matmul, module_float_dtype, param_dtype
from .._parametrisation import setting
from .network import check_learning, forward, lagged, logsig, output_layer_least_squares, random_hidden_layer


class NarxNetwork(AbstractCell):
    r"""NARX model $y_k = F(y_{k-1}, \ldots, y_{k-n_y},\; x_{k-d}, \ldots, x_{k-d-n_x+1})$ with $F$ a one-hidden-layer
    network (paper 002, eq. 10–11 with the BP network of eq. 13–16).

    On normalised signals $\tilde y = (y - y_0)/s_y$, $\tilde x = (x - x_0)/s_x$ and the regressor vector $z_k$ of
    the lags above: $O_j = g(\sum_i \omega_{ij} z_i + c_j)$ with the log-sigmoid $g$ (eq. 13, 15) and
    $\tilde y_k = \sum_j \omega_j O_j + b$ (eq. 16). Eq. (10) has $d = 1$ (no direct feed-through); $d = 0$ lets
    $x_k$ act on $y_k$. The biases $c_j$, $b$ are the ADALINEs' weights on a constant input. Eq. (13) names the
    log-sigmoid for the output layer too, but eq. (16) is linear and so is the output here (a sigmoid output would
    bound $y$).

    It is a cell over the input: `init(y0, x0)`, `step(state, x_k) -> (state, y_k)`; `simulate(x)` (also
    `__call__`) runs it free (parallel model, its own past outputs fed back); `one_step(x, y)` predicts each sample
    from the measured past (series-parallel model). The weights are the parameters (`fitting.fit` frees them); the
    normalisation is a setting.

    **Arguments:**

    - `key`: a PRNG key for the hidden layer ($\omega_{ij} \sim N(0, 1/n)$, $c_j \sim N(0, 1)$); the output weights
      start at 0, so the initial model predicts $y_0$.
    - `hidden`: $P$, the number of hidden ADALINEs; `output_lags` $n_y \ge 0$; `input_lags` $n_x \ge 1$;
      `delay` $d \ge 0$ (default 1).
    - `output_offset`, `output_scale`, `input_offset`, `input_scale`: $y_0, s_y, x_0, s_x$ ($s > 0$).

    ```python
    net = pj.NarxNetwork(jax.random.key(0), hidden=8, output_lags=2, input_lags=2, input_offset=100.0,
                         input_scale=50.0, output_scale=3e-6)
    result = fitting.fit(net, dataset, predictor=fitting.Predictor(lambda m, d: {"displacement": m(d.v_in)},
                                                                   ("displacement",)))
    ```
    """

    hidden_weights: Float[Array, "hidden inputs"]
    hidden_bias: Float[Array, " hidden"]
    output_weights: Float[Array, " hidden"]
    output_bias: Float[Array, ""]
    output_offset: Float[Array, ""] = setting()
    output_scale: Float[Array, ""] = setting()
    input_offset: Float[Array, ""] = setting()
    input_scale: Float[Array, ""] = setting()
    output_lags: int = eqx.field(static=True)
    input_lags: int = eqx.field(static=True)
    delay: int = eqx.field(static=True)

    def __init__(
        self,
        key: PRNGKeyArray,
        *,
        hidden: int,
        output_lags: int,
        input_lags: int,
        delay: int = 1,
        output_offset: ArrayLike = 0.0,
        output_scale: ArrayLike = 1.0,
        input_offset: ArrayLike = 0.0,
        input_scale: ArrayLike = 1.0,
    ):
        for name, value, least in (("output_lags", output_lags, 0), ("input_lags", input_lags, 1), ("delay", delay, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise PiezojaxValueError(f"`{name}` must be an int >= {least}, got {value!r}")
        self.output_lags, self.input_lags, self.delay = output_lags, input_lags, delay
        dtype = param_dtype(output_offset, output_scale, input_offset, input_scale)
        self.output_offset = check_scalar_param(output_offset, "output_offset", dtype)
        self.input_offset = check_scalar_param(input_offset, "input_offset", dtype)
        self.output_scale = check_value(check_scalar_param(output_scale, "output_scale", dtype), lambda s: s > 0,
                                        "`output_scale` must be > 0")
        self.input_scale = check_value(check_scalar_param(input_scale, "input_scale", dtype), lambda s: s > 0,
                                       "`input_scale` must be > 0")
        dtype = self.output_scale.dtype
        self.hidden_weights, self.hidden_bias = random_hidden_layer(key, hidden, output_lags + input_lags, dtype)
        self.output_weights = jnp.zeros((hidden,), dtype)
        self.output_bias = jnp.zeros((), dtype)

    @property
    def params(self) -> tuple[Array, Array, Array, Array]:
        """The weights `(W, c, w, b)`."""
        return self.hidden_weights, self.hidden_bias, self.output_weights, self.output_bias

    def with_params(self, params: tuple[Array, Array, Array, Array]) -> "NarxNetwork":
        """The same model with the weights `params = (W, c, w, b)`."""
        return eqx.tree_at(lambda m: m.params, self, tuple(params))

    def _prepare(self, *signals: SignalLike):
        dtype = module_float_dtype(self, *signals)
        names = ("x", "y")
        out = [check_signal(s, names[i], dtype) for i, s in enumerate(signals)]
        if len(out) == 2 and out[0].shape != out[1].shape:
            raise PiezojaxValueError(f"`x` and `y` must have the same length, got {out[0].shape} and {out[1].shape}")
        return cast_module(self, dtype), out

    def regressors(self, x: SignalLike, y: SignalLike) -> Float[Array, "time inputs"]:
        r"""The normalised regressors $z_k$ of every sample from measured `x`, `y` (before the record: the first
        samples), shape `(time, n_y + n_x)`."""
        m, (x, y) = self._prepare(x, y)
        yn = (y - m.output_offset) / m.output_scale
        xn = (x - m.input_offset) / m.input_scale
        return jnp.concatenate([lagged(yn, range(1, m.output_lags + 1)),
                                lagged(xn, range(m.delay, m.delay + m.input_lags))], axis=1)

    def one_step(self, x: SignalLike, y: SignalLike) -> Signal:
        """Series-parallel predictions $\\hat y_k = F(y_{k-1}, \\ldots; x_{k-d}, \\ldots)$ from the measured past."""
        m, (x, y) = self._prepare(x, y)
        z = m.regressors(x, y)
        return m.output_offset + m.output_scale * jax.vmap(lambda zk: forward(m.params, zk)[1])(z)

    def fit_output_layer(self, x: SignalLike, y: SignalLike, ridge: float = 1e-8) -> "NarxNetwork":
        r"""A start for training: the output weights $(\omega_j, b)$ by linear least squares on the one-step
        regression $\tilde y_k \approx \sum_j \omega_j O_j(z_k) + b$ of the measured `x`, `y` (ridge `ridge`,
        relative), the hidden layer kept as it is.

        **Returns:** the model with the fitted output layer.
        """
        m, (x, y) = self._prepare(x, y)
        hidden = logsig(matmul(m.regressors(x, y), m.hidden_weights.T) + m.hidden_bias)
        layer = output_layer_least_squares(hidden, (y - m.output_offset) / m.output_scale, ridge)
        return eqx.tree_at(lambda n: (n.output_weights, n.output_bias), m, layer)

    def init(self, y0: ArrayLike | None = None, x0: ArrayLike | None = None) -> tuple[Array, Array]:
        """The state `(past outputs (n_y,), past inputs (d + n_x,))`, at rest at `y0`, `x0` (default the
        offsets)."""
        dtype = self.output_scale.dtype
        y0 = self.output_offset if y0 is None else jnp.asarray(y0, dtype)
        x0 = self.input_offset if x0 is None else jnp.asarray(x0, dtype)
        yn = jnp.full((self.output_lags,), (y0 - self.output_offset) / self.output_scale, dtype)
        xn = jnp.full((self.delay + self.input_lags,), (x0 - self.input_offset) / self.input_scale, dtype)
        return yn, xn

    def step(self, state: tuple[Array, Array], x: Array) -> tuple[tuple[Array, Array], Array]:
        """Take $x_k$; return `(state, y_k)` with $y_k$ from the model's own past outputs."""
        ys, xs = state
        xs = jnp.concatenate([((x - self.input_offset) / self.input_scale)[None], xs[:-1]])
        z = jnp.concatenate([ys, xs[self.delay:]])
        yn = forward(self.params, z)[1]
        ys = jnp.concatenate([yn[None], ys[:-1]]) if self.output_lags else ys  # n_y = 0: no output lags to shift
        return (ys, xs), self.output_offset + self.output_scale * yn

    def simulate(self, x: SignalLike, y0: ArrayLike | None = None) -> Signal:
        """Free-run (parallel) simulation for the input `x`, from rest at `y0` (default the output offset) with the
        input at `x[0]`."""
        m, (x,) = self._prepare(x)
        return jax.lax.scan(lambda s, xk: m.step(s, xk), m.init(y0, x[0]), x)[1]

    def __call__(self, x: SignalLike, y0: ArrayLike | None = None) -> Signal:
        """Same as `simulate`."""
        return self.simulate(x, y0)


def train_narx_online(
    network: NarxNetwork,
    x: SignalLike,
    y: SignalLike,
    *,
    learning_rate: ArrayLike,
    momentum: ArrayLike = 0.0,
    epochs: int = 1,
) -> NarxNetwork:
    r"""Back-propagation as paper 002 trains its network: sample by sample through the record, gradient descent on
    the one-step error $\frac12 (\tilde y_k - F(z_k))^2$ with momentum,
    $\Delta\theta(k) = -\eta\,\nabla_\theta \tfrac12 e_k^2 + \alpha\,\Delta\theta(k-1)$ (the form of eq. 18–19).

    **Arguments:** `network`; the measured input `x` and output `y`; `learning_rate` $\eta \ge 0$; `momentum`
    $\alpha \in [0, 1)$ (scalars); `epochs`: passes through the record.

    **Returns:** the trained `NarxNetwork`.
    """
    if isinstance(epochs, bool) or not isinstance(epochs, int) or epochs < 1:
        raise PiezojaxValueError(f"`epochs` must be a positive int, got {epochs!r}")
    m, (x, y) = network._prepare(x, y)
    dtype = m.output_scale.dtype
    z = m.regressors(x, y)
    target = (y - m.output_offset) / m.output_scale
    eta, alpha = check_learning(check_scalar_param(learning_rate, "learning_rate", dtype),
                                check_scalar_param(momentum, "momentum", dtype))
    grad = jax.grad(lambda p, zk, tk: 0.5 * (tk - forward(p, zk)[1]) ** 2)

    def sample(carry, zt):
        params, delta = carry
        g = grad(params, *zt)
        delta = jax.tree_util.tree_map(lambda gi, di: -eta * gi + alpha * di, g, delta)
        return (jax.tree_util.tree_map(jnp.add, params, delta), delta), None

    def epoch(carry, _):
        return jax.lax.scan(sample, carry, (z, target))[0], None

    zeros = jax.tree_util.tree_map(jnp.zeros_like, m.params)
    (params, _), _ = jax.lax.scan(epoch, (m.params, zeros), None, length=epochs)
    return m.with_params(params)
