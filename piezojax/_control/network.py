"""The one-hidden-layer network of paper 002 (eq. 13–16), shared by the NARX model and the adaptive controller."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, PRNGKeyArray

from .._checks import PiezojaxValueError, check_value
from .._dtypes import matmul


def check_learning(learning_rate: Array, momentum: Array) -> tuple[Array, Array]:
    r"""Online back-propagation's learning rate $\eta \ge 0$ and momentum $\alpha \in [0, 1)$ (eq. 18–19), checked
    (`check_value`)."""
    eta = check_value(learning_rate, lambda a: a >= 0, "`learning_rate` must be >= 0")
    alpha = check_value(momentum, lambda a: (a >= 0) & (a < 1), "`momentum` must be in [0, 1)")
    return eta, alpha


def logsig(z: Array) -> Array:
    r"""The log-sigmoid $g(z) = 1/(1 + e^{-z})$ of eq. (13)."""
    return jax.nn.sigmoid(z)


def forward(params: tuple[Array, Array, Array, Array], z: Array) -> tuple[Array, Array]:
    r"""Hidden outputs $O_j = g(\sum_i \omega_{ij} z_i + c_j)$ (eq. 15) and the linear output
    $\sum_j \omega_j O_j + b$ (eq. 16), for `params = (W (P, n), c (P,), w (P,), b ())`."""
    W, c, w, b = params
    hidden = logsig(matmul(W, z) + c)
    return hidden, matmul(w, hidden) + b


def random_hidden_layer(key: PRNGKeyArray, hidden: int, inputs: int, dtype) -> tuple[Array, Array]:
    """Hidden weights $\\sim N(0, 1/n)$ and biases $\\sim N(0, 1)$ for $n$ normalised inputs."""
    if not isinstance(hidden, int) or isinstance(hidden, bool) or hidden < 1:
        raise PiezojaxValueError(f"`hidden` must be a positive int, got {hidden!r}")
    typed = hasattr(key, "dtype") and jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
    raw = hasattr(key, "dtype") and key.dtype == jnp.uint32 and jnp.ndim(key) == 1  # PRNGKey(0), any impl
    if not (typed and jnp.shape(key) == ()) and not raw:
        raise PiezojaxValueError(f"`key` must be one JAX PRNG key (jax.random.key(0) or jax.random.PRNGKey(0)), got "
                                 f"{type(key).__name__} {getattr(key, 'dtype', '')} of shape {jnp.shape(key)}")
    kw, kc = jax.random.split(key)
    W = jax.random.normal(kw, (hidden, inputs), dtype) / jnp.sqrt(jnp.asarray(inputs, dtype))
    return W, jax.random.normal(kc, (hidden,), dtype)


def lagged(s: Array, lags: range) -> Array:
    """Columns $s_{k-j}$ for $j$ in `lags`, shape `(time, len(lags))`; before the record, $s_{k<0} = s_0$."""
    n = s.shape[0]
    cols = [s if j == 0 else jnp.concatenate([jnp.full((min(j, n),), s[0], s.dtype), s[: max(n - j, 0)]])
            for j in lags]
    return jnp.stack(cols, axis=1) if cols else jnp.zeros((n, 0), s.dtype)


def output_layer_least_squares(hidden: Array, target: Array, ridge: float) -> tuple[Array, Array]:
    r"""Output weights and bias $(\omega, b)$ minimising $\|O\omega + b - t\|^2 + \lambda\|(\omega, b)\|^2$ for hidden
    outputs `hidden` (time, P) and `target` (time,), with $\lambda$ = `ridge` × the mean diagonal of the normal
    matrix."""
    A = jnp.concatenate([hidden, jnp.ones((hidden.shape[0], 1), hidden.dtype)], axis=1)
    lam = ridge * jnp.trace(matmul(A.T, A)) / A.shape[1]
    sol = jnp.linalg.solve(matmul(A.T, A) + lam * jnp.eye(A.shape[1], dtype=A.dtype), matmul(A.T, target))
    return sol[:-1], sol[-1]
