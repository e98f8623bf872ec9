"""The continuous-time SISO linear system interface."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from .._checks import as_float_array, check_signal
from .._custom_types import Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype
from .discretise import DiscreteStateSpace, check_hold, discretise_state_space


class AbstractLinearSystem(eqx.Module):
    r"""A continuous-time, single-input single-output linear time-invariant system.

    $\dot x = A x + B u$, $\quad y = C x + D u$, $\quad G(s) = C (sI - A)^{-1} B + D$.

    A concrete system defines `state_space()`, its continuous-time realisation. Everything else is shared:
    exact discretisation (`discretise`), simulation of a sampled input by `lax.scan` (`simulate`, `scan`),
    `dc_gain()`, `frequency_response(w)` and `order`.

    Sampled inputs are held between samples by `hold="zoh"` (constant, as a DAC does) or `"foh"` (linear,
    as `scipy.signal.lsim` does by default). The discretisation is exact for that input (matrix exponential).

    Checks: constructors reject complex or boolean coefficients and NaN/inf values with a `PiezojaxValueError`
    naming the argument (`eqx.error_if` for traced values); the input `u` must be real, 1-D and finite; the
    realisation is checked again whenever it is built (`state_space()`), so coefficients replaced after
    construction (`eqx.tree_at`) are caught too.
    """

    @abc.abstractmethod
    def state_space(self) -> tuple[Float[Array, "n n"], Float[Array, " n"], Float[Array, " n"], Float[Array, ""]]:
        """The continuous-time realisation `(A (n, n), B (n,), C (n,), D ())`."""

    @property
    def order(self) -> int:
        """The number of states n (static)."""
        return jax.eval_shape(lambda m: m.state_space()[0], self).shape[0]

    def dc_gain(self) -> Float[Array, ""]:
        r"""The static gain $G(0) = D - C A^{-1} B$ (infinite or NaN if the system has a pole at 0)."""
        A, B, C, D = self.state_space()
        if A.shape[0] == 0:
            return D
        return D - jnp.dot(C, jnp.linalg.solve(A, B))

    def equilibrium_state(self, u0: ArrayLike) -> Float[Array, " n"]:
        r"""The state of `state_space()` at rest under the constant input `u0`: $x = -A^{-1} B u_0$.

        `simulate(u, dt, x0=sys.equilibrium_state(c))` starts the system settled at the input $c$ (output
        $G(0)\,c$ until the input moves). Needs $A$ invertible (no pole at 0).
        """
        A, B, _, _ = self.state_space()
        u0 = jnp.asarray(u0, A.dtype)
        if A.shape[0] == 0:
            return jnp.zeros((0,), A.dtype)
        return -jnp.linalg.solve(A, B) * u0

    def frequency_response(self, w: Float[ArrayLike, " freq"]) -> Complex[Array, " freq"]:
        r"""$G(j\omega) = C (j\omega I - A)^{-1} B + D$ at angular frequencies `w` (rad/s)."""
        A, B, C, D = self.state_space()
        w = as_float_array(w, "w", A.dtype)
        ctype = jnp.complex128 if A.dtype == jnp.float64 else jnp.complex64
        n = A.shape[0]

        def one(wi):
            M = jax.lax.complex(jnp.zeros_like(wi), wi) * jnp.eye(n, dtype=ctype) - A.astype(ctype)
            return jnp.dot(C.astype(ctype), jnp.linalg.solve(M, B.astype(ctype))) + D.astype(ctype)

        return jax.vmap(one)(jnp.atleast_1d(w)).reshape(w.shape)

    def discretise(self, dt: ArrayLike, hold: str = "zoh") -> DiscreteStateSpace:
        r"""Exact discretisation for a sampled input held by `hold` (see `discretise_state_space`).

        **Arguments:**

        - `dt`: sampling step in s (> 0).
        - `hold`: `"zoh"` or `"foh"`.

        **Returns:** a `DiscreteStateSpace` with fields `Ad, Bd, Cd, Dd` equal to
        `scipy.signal.cont2discrete(self.state_space(), dt, method=hold)`.
        """
        return discretise_state_space(*self.state_space(), dt, hold)

    def scan(
        self, u: SignalLike, dt: ArrayLike, state: ArrayLike | None = None, hold: str = "zoh"
    ) -> tuple[Float[Array, " n"], Signal]:
        r"""Simulate from a *discrete* state and return it after the last sample, for chunked simulation.

        `state` is the state $\xi$ of `discretise(dt, hold)` (the continuous state for ZOH; $x - \Gamma_1 u$ for
        FOH); default: at rest ($x = 0$) at the first sample, as `simulate`. Passing the returned state to the next
        call with the following samples continues the record exactly.

        **Returns:** `(state_N, y)`.
        """
        check_hold(hold)
        dtype = module_float_dtype(self, u)
        u = check_signal(u, "u", dtype)
        d = cast_module(self, dtype).discretise(dt, hold)
        if state is None:
            state = d.init_state(None, u[0])
        return d.scan(u, state)

    def simulate(self, u: SignalLike, dt: ArrayLike, x0: ArrayLike | None = None, hold: str = "zoh") -> Signal:
        r"""The output $y_k = y(k\,dt)$ for input samples $u_k$, from the continuous state `x0` at $t_0$.

        $x_{k+1} = A_d x_k + \ldots$ (exact for the held input), scanned with `jax.lax.scan`.

        **Arguments:**

        - `u`: real, finite input samples, shape `(time,)` (use `jax.vmap` for a batch).
        - `dt`: sampling step in s (> 0).
        - `x0`: state of `state_space()` at the first sample, shape `(n,)`; default zeros (system at rest).
        - `hold`: `"zoh"` (default) or `"foh"` (matches `scipy.signal.lsim`).

        **Returns:** the output samples, shape `(time,)`.

        ```python
        G = pj.TransferFunction([1.0], [1e-3, 1.0])       # first-order lag, tau = 1 ms
        y = G.simulate(jnp.ones(1000), 1e-5)              # step response 1 - exp(-t/tau) at t = k dt
        ```
        """
        check_hold(hold)
        dtype = module_float_dtype(self, u)
        u = check_signal(u, "u", dtype)
        d = cast_module(self, dtype).discretise(dt, hold)
        return d.scan(u, None if x0 is None else d.init_state(x0, u[0]))[1]

    def __call__(self, u: SignalLike, dt: ArrayLike, x0: ArrayLike | None = None, hold: str = "zoh") -> Signal:
        """Same as `simulate`."""
        return self.simulate(u, dt, x0, hold)
