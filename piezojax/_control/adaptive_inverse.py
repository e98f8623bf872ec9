"""Paper 002's nonlinear adaptive inverse controller: a NARMAX network adapted online (eq. 12–19)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import PiezojaxValueError, check_scalar_param, check_signal, check_value, error_if_not_finite
from .._dtypes import matmul, module_float_dtype, param_dtype
from .._parametrisation import setting
from .base import AbstractController, check_limits
from .network import check_learning, forward, lagged, logsig, output_layer_least_squares, random_hidden_layer


class AdaptiveInverseController(AbstractController):
    r"""Nonlinear adaptive inverse control (paper 002, Fig. 16–18, eq. 12–19): a one-hidden-layer network maps the
    recent measured outputs and references to the command, and learns online from the tracking error.

    **Our reading of the paper's indices.** The input vector (eq. 12) is
    $X_k = \{\tilde y_k, \ldots, \tilde y_{k-n_y+1};\ \tilde r_k, \ldots, \tilde r_{k-n_r+1}\}$, normalised as
    $\tilde y = (y - y_0)/s_y$. The paper writes $\bar y(k-1), \bar y_d(k-1), \ldots$ because its $\bar y(k)$ is the
    response to $u(k)$; in a sampled loop (`pj.closed_loop`) that response is read one instant later, so the
    newest measurement and reference at step $k$ carry the same information. Hidden outputs
    $O_j(k) = g(\sum_i \omega_{ij} X_i(k) + c_j)$ (eq. 13, 15), command
    $u_k = u_0 + s_u \left(\sum_j \omega_j O_j(k) + b\right)$ (eq. 16), clipped to $[u_{\min}, u_{\max}]$.

    **Online update (eq. 17–19).** At step $k$ the error of the previous command's result is
    $e = (r_k - y_k)/s_y$ (eq. 17), and before computing $u_k$ the weights move by

    $\omega_j \mathrel{+}= \eta\, e\, O_j(k-1) + \alpha\,[\omega_j(k-1) - \omega_j(k-2)]$ (eq. 18),

    $\omega_{ij} \mathrel{+}= \eta\, e\, \omega_j(k-1)\, g'(\cdot)\, X_i(k-1) + \alpha\,[\omega_{ij}(k-1) -
    \omega_{ij}(k-2)]$ (eq. 19),

    with $g' = g(1 - g)$ at the hidden layer's activation of step $k-1$ (the paper's garbled eq. 19 reads
    $g[\cdot]$; its derivative is what back-propagation gives), and the biases updated as weights on a constant
    input 1. This is the gradient of $\frac12 e^2$ with the plant's sensitivity $\partial y/\partial u$ replaced
    by $+1$ (its sign for a piezo stage with $s_u > 0$; $\eta$ absorbs its size). `learning_rate=0` freezes the
    network (a fixed NARMAX inverse).

    **Arguments:**

    - `key`: PRNG key for the hidden layer; the output weights start at 0 (the command starts at $u_0$).
      `fit_output_layer` gives them an offline start from an open-loop record.
    - `hidden`: $P$; `measurement_lags` $n_y \ge 0$; `reference_lags` $n_r \ge 1$.
    - `learning_rate` $\eta \ge 0$, `momentum` $\alpha \in [0, 1)$.
    - `offset` $u_0$ and `command_scale` $s_u > 0$ [command units]; `output_offset` $y_0$ and `output_scale`
      $s_y > 0$ [measurement units].
    - `u_min`, `u_max`: command limits (default unbounded).
    - `preview`: $p \ge 0$, the `preview` of the `pj.closed_loop` this controller runs in: the reference read at
      step $k$ is then $r_{k+p}$, and the error of eq. (17) compares $y_k$ with the reference read $p$ steps
      earlier (the one aimed at instant $k$). Use `preview=1` with `pj.closed_loop(..., preview=1)`: the command
      $u_k$ shows in the measurement at $k+1$, so the network then reads the reference it is to reach (and
      `fit_output_layer` fits exactly that map); with 0 it aims one sample late.

    ```python
    aic = pj.AdaptiveInverseController(jax.random.key(0), hidden=8, learning_rate=0.05, momentum=0.5,
                                       offset=100.0, command_scale=50.0, output_scale=3e-6, preview=1)
    rec = pj.closed_loop(aic, plant, reference, observer=observer, preview=1)
    ```
    """

    hidden_weights: Float[Array, "hidden inputs"]
    hidden_bias: Float[Array, " hidden"]
    output_weights: Float[Array, " hidden"]
    output_bias: Float[Array, ""]
    learning_rate: Float[Array, ""] = setting()
    momentum: Float[Array, ""] = setting()
    offset: Float[Array, ""] = setting()
    command_scale: Float[Array, ""] = setting()
    output_offset: Float[Array, ""] = setting()
    output_scale: Float[Array, ""] = setting()
    u_min: Float[Array, ""] = setting()
    u_max: Float[Array, ""] = setting()
    measurement_lags: int = eqx.field(static=True)
    reference_lags: int = eqx.field(static=True)
    preview: int = eqx.field(static=True)

    def __init__(
        self,
        key: PRNGKeyArray,
        *,
        hidden: int,
        measurement_lags: int = 2,
        reference_lags: int = 2,
        learning_rate: ArrayLike = 0.0,
        momentum: ArrayLike = 0.0,
        offset: ArrayLike = 0.0,
        command_scale: ArrayLike = 1.0,
        output_offset: ArrayLike = 0.0,
        output_scale: ArrayLike = 1.0,
        u_min: ArrayLike = -jnp.inf,
        u_max: ArrayLike = jnp.inf,
        preview: int = 0,
    ):
        for name, value, least in (("measurement_lags", measurement_lags, 0), ("reference_lags", reference_lags, 1),
                                   ("preview", preview, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise PiezojaxValueError(f"`{name}` must be an int >= {least}, got {value!r}")
        self.measurement_lags, self.reference_lags, self.preview = measurement_lags, reference_lags, preview
        dtype = param_dtype(learning_rate, momentum, offset, command_scale, output_offset, output_scale, u_min, u_max)
        self.learning_rate = check_scalar_param(learning_rate, "learning_rate", dtype)
        self.momentum = check_scalar_param(momentum, "momentum", dtype)
        self.offset = check_scalar_param(offset, "offset", dtype)
        self.command_scale = check_scalar_param(command_scale, "command_scale", dtype)
        self.output_offset = check_scalar_param(output_offset, "output_offset", dtype)
        self.output_scale = check_scalar_param(output_scale, "output_scale", dtype)
        self.u_min = check_scalar_param(u_min, "u_min", dtype, finite=False)
        self.u_max = check_scalar_param(u_max, "u_max", dtype, finite=False)
        checked = self._checked_settings()
        (self.learning_rate, self.momentum, self.command_scale, self.output_scale, self.u_min, self.u_max) = checked
        self.hidden_weights, self.hidden_bias = random_hidden_layer(
            key, hidden, measurement_lags + reference_lags, dtype
        )
        self.output_weights = jnp.zeros((hidden,), dtype)
        self.output_bias = jnp.zeros((), dtype)

    def _checked_settings(self) -> tuple[Array, ...]:
        learning_rate, momentum = check_learning(self.learning_rate, self.momentum)
        command_scale = check_value(self.command_scale, lambda a: a > 0, "`command_scale` must be > 0")
        output_scale = check_value(self.output_scale, lambda a: a > 0, "`output_scale` must be > 0")
        return (learning_rate, momentum, command_scale, output_scale, *check_limits(self.u_min, self.u_max))

    def check(self) -> "AdaptiveInverseController":
        m = error_if_not_finite(self, ("learning_rate", "momentum", "offset", "command_scale", "output_offset",
                                       "output_scale", "hidden_weights", "hidden_bias", "output_weights",
                                       "output_bias"))
        return eqx.tree_at(lambda c: (c.learning_rate, c.momentum, c.command_scale, c.output_scale, c.u_min,
                                      c.u_max), m, m._checked_settings())

    @property
    def params(self) -> tuple[Array, Array, Array, Array]:
        """The initial weights `(W, c, w, b)` (the state carries the adapted ones)."""
        return self.hidden_weights, self.hidden_bias, self.output_weights, self.output_bias

    def _normalise(self, y: Array) -> Array:
        return (y - self.output_offset) / self.output_scale

    def init(self):
        """The state `(weights, last weight change, past y, past r, X_{k-1}, O_{k-1}, started, targets)`."""
        dtype = self.output_scale.dtype
        n_in = self.measurement_lags + self.reference_lags
        params = self.params
        return (
            params,
            jax.tree_util.tree_map(jnp.zeros_like, params),
            jnp.zeros((self.measurement_lags,), dtype),
            jnp.zeros((self.reference_lags,), dtype),
            jnp.zeros((n_in,), dtype),
            jnp.zeros(self.hidden_bias.shape, dtype),
            jnp.zeros((), dtype),
            jnp.zeros((self.preview,), dtype),
        )

    def step(self, state, reference, measurement):
        params, delta, ys, rs, x_prev, o_prev, started, targets = state
        W, c, w, b = params
        yn, rn = self._normalise(measurement), self._normalise(reference)
        # the reference read `preview` samples ago is the one the measurement of this instant is compared with;
        # until `preview` references have been read, that is the first one read (the controller never sees the
        # record's first `preview` references: it reads ahead from its start, so the reference counts as constant
        # before it; with a reference that starts at rest this changes nothing)
        targets = jnp.where(started > 0, targets, jnp.full_like(targets, rn))
        target = targets[-1] if self.preview else rn
        targets = jnp.concatenate([rn[None], targets[:-1]]) if self.preview else targets
        # eq. (17)–(19): the error of the previous command's result, back-propagated through the network that
        # produced it (the weights of step k-1, its inputs and hidden outputs); nothing to learn at the first step.
        e = started * (target - yn)
        slope = o_prev * (1 - o_prev)
        grad_w, grad_b = e * o_prev, e
        grad_c = e * w * slope
        grad_W = grad_c[:, None] * x_prev[None, :]
        delta = jax.tree_util.tree_map(
            lambda g, d: self.learning_rate * g + self.momentum * d, (grad_W, grad_c, grad_w, grad_b), delta
        )
        params = jax.tree_util.tree_map(jnp.add, params, delta)
        if self.measurement_lags:
            ys = jnp.concatenate([yn[None], ys[:-1]])
        ys = jnp.where(started > 0, ys, jnp.full_like(ys, yn))  # at rest before the first sample
        rs = jnp.where(started > 0, jnp.concatenate([rn[None], rs[:-1]]), jnp.full_like(rs, rn))
        x = jnp.concatenate([ys, rs])
        hidden, out = forward(params, x)
        u = jnp.clip(self.offset + self.command_scale * out, self.u_min, self.u_max)
        return (params, delta, ys, rs, x, hidden, jnp.ones_like(started), targets), u

    def fit_output_layer(
        self, measurement: ArrayLike, command: ArrayLike, ridge: float = 1e-6
    ) -> "AdaptiveInverseController":
        r"""An offline start from an open-loop record: the output weights $(\omega_j, b)$ by linear least squares
        (ridge `ridge`, relative), so that the network maps $X_k$ built from the record to the command that
        produced the next measurement: $u_k \approx u_0 + s_u(\sum_j \omega_j O_j(X_k) + b)$ with the references
        newest reference replaced by the measured $y_{k+s}$, $s = \max(p, 1)$ with $p$ = `preview`, and the older
        ones by $y_{k+s-1}, \ldots$ (direct inverse learning). With `preview=1` this is the inverse the loop uses
        (the network reads $r_{k+1}$ to command $u_k$); with `preview=0` the loop feeds it $r_k$, one sample
        late. The hidden layer stays random.

        **Arguments:** `measurement` $y_k$ and `command` $u_k$ (same length, $y_{k+1}$ the response to $u_k$).

        **Returns:** the controller with the fitted output layer.
        """
        dtype = module_float_dtype(self, measurement, command)
        y = check_signal(measurement, "measurement", dtype)
        u = check_signal(command, "command", dtype)
        if y.shape != u.shape or y.shape[0] < 3:
            raise PiezojaxValueError(
                f"`measurement` and `command` must have the same length >= 3, got {y.shape} and {u.shape}"
            )
        shift = max(self.preview, 1)
        if y.shape[0] < shift + 3:
            raise PiezojaxValueError(f"the record must be longer than `preview` + 2 samples, got {y.shape[0]}")
        yn = self._normalise(y)
        n = y.shape[0] - shift
        x = jnp.concatenate([lagged(yn[:n], range(self.measurement_lags)),
                             lagged(yn[shift:], range(self.reference_lags))], axis=1)
        W, c = self.hidden_weights.astype(dtype), self.hidden_bias.astype(dtype)
        hidden = logsig(matmul(x, W.T) + c)
        layer = output_layer_least_squares(hidden, (u[:n] - self.offset) / self.command_scale, ridge)
        return eqx.tree_at(lambda m: (m.output_weights, m.output_bias), self, layer)
