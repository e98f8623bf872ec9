"""The cell interfaces of a closed loop: controllers and plants."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, PyTree

from .._checks import PiezojaxValueError, check_finite, check_signal, check_value
from .._custom_types import Signal, SignalLike
from .._dtypes import cast_module, module_float_dtype


class AbstractController(eqx.Module):
    r"""A discrete-time controller as a cell: `init() -> state`, `step(state, r_k, y_k) -> (state, u_k)`.

    At each sample $k$ the controller reads the reference $r_k$ and the feedback $y_k$ (the plant's measured or
    estimated output at that instant, which depends on the commands up to $u_{k-1}$ only) and returns the command
    $u_k$, held until the next sample. `pj.closed_loop` scans a controller with a plant and an observer; `__call__`
    replays a controller against recorded signals (open loop).

    Concrete controllers: `pj.PID`, `pj.InverseFeedforward`, `pj.FeedforwardFeedback`,
    `pj.AdaptiveInverseController`. A controller of one's own defines `init`, `step` and `check` (the checks of its
    settings, run by every loop and replay; one with nothing to check returns `self`):

    ```python
    class Proportional(pj.AbstractController):
        k: jax.Array

        def init(self):
            return ()

        def step(self, state, reference, measurement):
            return state, self.k * (reference - measurement)

        def check(self):
            return self
    ```
    """

    @abc.abstractmethod
    def init(self) -> PyTree[Array]:
        """The state before the first sample."""

    @abc.abstractmethod
    def step(self, state: PyTree[Array], reference: Array, measurement: Array) -> tuple[PyTree[Array], Array]:
        """Read $r_k$ and $y_k$; return `(state, u_k)`."""

    @abc.abstractmethod
    def check(self) -> "AbstractController":
        """Return `self` with its parameter value checks attached (raised now if concrete, `eqx.error_if` if
        traced): `__call__` and `pj.closed_loop` run it, so a parameter replaced after construction (`eqx.tree_at`)
        is checked too. With nothing to check: `return self`."""

    def __call__(self, reference: SignalLike, measurement: SignalLike) -> Signal:
        """The commands $u_k$ for recorded references and feedback signals (same length), from `init()`."""
        dtype = module_float_dtype(self, reference, measurement)
        r = check_signal(reference, "reference", dtype)
        y = check_signal(measurement, "measurement", dtype)
        if r.shape != y.shape:
            raise PiezojaxValueError(
                f"`reference` and `measurement` must have the same length, got {r.shape} and {y.shape}"
            )
        c = cast_module(self, dtype).check()
        return jax.lax.scan(lambda s, ry: c.step(s, ry[0], ry[1]), c.init(), (r, y))[1]


class AbstractPlant(eqx.Module):
    r"""A sampled plant as a cell in state-space form: $x_{k+1} = f(x_k, u_k)$, $\;y_k = h(x_k, w_k)$.

    `output(state, noise)` is what the instruments read at the current instant (a dict of channels, e.g.
    `"v_in"`, `"v_out"`, `"displacement"`), with `noise` the exogenous sample $w_k$ (any pytree, or None);
    `step(state, u)` advances the state over one sample period with the command `u` held (a DAC). The output does
    not depend on the command of the same instant, so a loop has no algebraic loop.
    """

    @abc.abstractmethod
    def init(self) -> PyTree[Array]:
        """The state at rest before the first command."""

    @abc.abstractmethod
    def output(self, state: PyTree[Array], noise: PyTree[Array] | None) -> dict[str, Array]:
        """The channels measured at the current instant."""

    @abc.abstractmethod
    def step(self, state: PyTree[Array], command: Array) -> PyTree[Array]:
        """The state one sample period later, with `command` held."""

    def simulate(self, command: SignalLike, noise: PyTree[ArrayLike] | None = None) -> dict[str, Signal]:
        """Open loop: the channels at each instant $k$ (before $u_k$ acts) for the commands $u_k$, from `init()`.

        `noise`: a pytree whose leaves have a leading time axis of the same length (one $w_k$ per sample), or None.
        """
        dtype = module_float_dtype(self, command)
        u = check_signal(command, "command", dtype)
        p = cast_module(self, dtype)

        def body(state, uw):
            u_k, w_k = uw
            return p.step(state, u_k), p.output(state, w_k)

        return jax.lax.scan(body, p.init(), (u, noise))[1]


def as_time_major(tree: PyTree[ArrayLike] | None, n: int, name: str, dtype) -> PyTree[Array] | None:
    """Leaves of `tree` as arrays of `dtype` with a leading axis of length `n` (a ValueError naming `name` if not)."""
    if tree is None:
        return None

    def one(x):
        x = jnp.asarray(x, dtype)
        if x.ndim == 0 or x.shape[0] != n:
            raise PiezojaxValueError(
                f"every leaf of `{name}` must have a leading time axis of length {n}, got {x.shape}"
            )
        return check_finite(x, name)

    return jax.tree_util.tree_map(one, tree)


def check_limits(u_min: Array, u_max: Array) -> tuple[Array, Array]:
    """The command limits, checked: neither NaN, and `u_max` > `u_min`."""
    u_min = check_value(u_min, lambda v: ~jnp.isnan(v), "`u_min` must not be NaN")
    u_max = check_value(u_max, lambda v: ~jnp.isnan(v) & (v > u_min), "`u_max` must be greater than `u_min`")
    return u_min, u_max
