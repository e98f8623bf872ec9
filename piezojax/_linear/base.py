"""The continuous-time SISO linear system interface."""

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .._checks import (
    PiezojaxValueError,
    as_float_array,
    check_positive,
    check_scalar,
    check_signal,
    check_value,
    concrete_or_none,
)
from .._custom_types import Signal, SignalLike
from .._dtypes import cast_module, matmul, module_float_dtype
from .discretise import DiscreteStateSpace, check_hold, check_realisation, discretise_state_space


class AbstractLinearSystem(eqx.Module):
    r"""A continuous-time, single-input single-output linear time-invariant system.

    $\dot x = A x + B u$, $\quad y = C x + D u$, $\quad G(s) = C (sI - A)^{-1} B + D$.

    A concrete system defines `state_space()`, its continuous-time realisation, and `order`, its number of states.
    Everything else is shared: exact discretisation (`discretise`), simulation of a sampled input by `lax.scan`
    (`simulate`, `scan`), `dc_gain()` and `frequency_response(w)`.

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
    @abc.abstractmethod
    def order(self) -> int:
        """The number of states n (static): the size of `state_space()`'s `A`."""

    def dc_gain(self) -> Float[Array, ""]:
        r"""The static gain $G(0) = D - C A^{-1} B$ (infinite or NaN if the system has a pole at 0)."""
        A, B, C, D = self.state_space()
        if A.shape[0] == 0:
            return D
        return D - matmul(C, jnp.linalg.solve(A, B))

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
            return matmul(C.astype(ctype), jnp.linalg.solve(M, B.astype(ctype))) + D.astype(ctype)

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

    def relative_degree(self, rtol: float = 1e-9) -> int:
        r"""The relative degree $r$ of $G(s)$: 0 if $D \ne 0$, else the first $i$ with $C A^{i-1} B \ne 0$.

        Terms are compared at the scale $\rho = \max|\lambda(A)|$ (the size of $C A^{i-1} B / s^i$ at $|s| = \rho$),
        a term counting as zero below `rtol` times the largest. Needs concrete values (`PiezojaxValueError` under
        `jit`: pass the degree explicitly where it is asked for).
        """
        A, B, C, D = (concrete_or_none(x) for x in self.state_space())
        if any(x is None for x in (A, B, C, D)):
            raise PiezojaxValueError(
                "the relative degree needs concrete system values, and these are traced (under jit, vmap or grad): "
                "pass `relative_degree` explicitly (and `bandwidth`, whose default needs them too)"
            )
        A, B, C, D = (np.asarray(x, np.float64) for x in (A, B, C, D))
        n = A.shape[0]
        rho = max(float(np.max(np.abs(np.linalg.eigvals(A)))) if n else 0.0, np.finfo(np.float64).tiny)
        terms, x = [abs(float(D))], B
        for _ in range(n):
            terms.append(abs(float(C @ x)))
            x = (A @ x) / rho
        scale = max(terms)
        if scale == 0:
            raise PiezojaxValueError("the system is identically zero: it has no relative degree and no inverse")
        return next(i for i, t in enumerate(terms) if t > rtol * scale)

    def inverse(
        self, bandwidth: ArrayLike | None = None, relative_degree: int | None = None
    ) -> "AbstractLinearSystem":
        r"""A stable, proper inverse $F(s)/G(s)$ with a unit-DC-gain low-pass $F(s) = (\omega_f/(s + \omega_f))^r$.

        $G$ of relative degree $r \ge 1$ (e.g. a resonance $K\omega^2/(s^2 + 2\zeta\omega s + \omega^2)$, $r = 2$) has
        no proper inverse: $1/G$ differentiates $r$ times. $F/G$ is proper, and it is realised without polynomials
        from $G$'s own realisation $(A, B, C, D)$: with $g = C A^{r-1} B$ and $p(s) = (s + \omega_f)^r = s^r + \sum_i
        a_i s^i$, the input $u = (a_0 y_{ref} - C\,p(A)\,x)/g$ with $\dot x = A x + B u$ makes $y = C x$ obey
        $p(d/dt)\,y = a_0 y_{ref}$, i.e. $y = F y_{ref}$ (since $y^{(i)} = C A^i x$ for $i < r$ and $y^{(r)} = C A^r x
        + g u$). So the inverse is the `StateSpace` $A - B\,C p(A)/g$, $B a_0/g$, $-C p(A)/g$, $a_0/g$, whose poles are
        the zeros of $G$ and $r$ poles at $-\omega_f$: stable exactly when $G$ is minimum phase (checked for
        concrete values: `PiezojaxValueError` otherwise). For $r = 0$ it is the exact inverse ($F = 1$).

        $F$ has no overshoot (critically damped) and delays slow signals by its group delay $r/\omega_f$; a
        feedforward that knows the reference in advance removes it by preview (`Actuator.inverse` does). The
        default $\omega_f = \max|\lambda(A)|$, the fastest pole: for a resonance, $|F/G|$ then stays below $1/K$ at
        every frequency (the inverse cancels the resonant peak and amplifies no noise above it); a higher
        bandwidth inverts $G$ further at the price of larger drive peaks.

        **Arguments:**

        - `bandwidth`: $\omega_f$ in rad/s (> 0); default the fastest pole (needs concrete values).
        - `relative_degree`: $r$; default `relative_degree()` (needs concrete values).

        **Returns:** a `StateSpace`, to `simulate` on the desired output (with `hold="foh"` for a sampled smooth
        reference).
        """
        A, B, C, D = self.state_space()
        n = A.shape[0]
        r = self.relative_degree() if relative_degree is None else relative_degree
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or not 0 <= r <= n:
            raise PiezojaxValueError(f"`relative_degree` must be an int in [0, {n}], got {r!r}")
        if r == 0:
            p_a, g, a0 = jnp.eye(n, dtype=A.dtype), D, jnp.ones((), A.dtype)
        else:
            if bandwidth is None:
                bandwidth = default_inverse_bandwidth(self)
            wf = check_positive(check_scalar(bandwidth, "bandwidth", A.dtype), "bandwidth")
            p_a, power = jnp.zeros_like(A), jnp.eye(n, dtype=A.dtype)
            for i in range(r + 1):
                p_a = p_a + math.comb(r, i) * wf ** (r - i) * power
                if i == r - 1:
                    g = matmul(matmul(C, power), B)
                power = matmul(power, A)
            a0 = wf**r
        g = check_value(g, lambda x: x != 0, f"`relative_degree` {r} does not match the system (C A^(r-1) B = 0)")
        c_p = matmul(C, p_a)
        inv = StateSpace(A - jnp.outer(B, c_p) / g, B * a0 / g, -c_p / g, a0 / g)
        a_i = concrete_or_none(inv.A)
        if a_i is not None and n and np.max(np.linalg.eigvals(np.asarray(a_i, np.float64)).real) >= 0:
            raise PiezojaxValueError(
                "the system has zeros with Re(s) >= 0 (non-minimum phase): its inverse is unstable"
            )
        return inv


def default_inverse_bandwidth(system: AbstractLinearSystem) -> float:
    r"""The default $\omega_f$ of `AbstractLinearSystem.inverse`: the fastest pole's magnitude $\max|\lambda(A)|$."""
    a = concrete_or_none(system.state_space()[0])
    if a is None:
        raise PiezojaxValueError("pass `bandwidth` when the system's values are traced (under jit, vmap or grad): "
                                 "the default needs concrete values")
    return float(np.max(np.abs(np.linalg.eigvals(np.asarray(a, np.float64)))))


class StateSpace(AbstractLinearSystem):
    r"""A SISO linear system given by a realisation: $\dot x = A x + B u$, $y = C x + D u$.

    The realisation is used as given (no balancing); for lightly damped or widely spread poles prefer a well-scaled
    (modal) realisation, e.g. `StableTransferFunction`.

    **Arguments:**

    - `A`: state matrix, shape `(n, n)`.
    - `B`: input vector, shape `(n,)`.
    - `C`: output vector, shape `(n,)`.
    - `D`: feedthrough, scalar (default 0).

    ```python
    G = pj.StateSpace([[-1.0]], [1.0], [2.0], 0.0)   # 2 / (s + 1)
    G.dc_gain()  # 2.0
    ```
    """

    A: Float[Array, "n n"]
    B: Float[Array, " n"]
    C: Float[Array, " n"]
    D: Float[Array, ""]

    def __init__(self, A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike = 0.0):
        self.A, self.B, self.C, self.D = check_realisation(A, B, C, D)

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def state_space(self):
        return self.A, self.B, self.C, self.D
