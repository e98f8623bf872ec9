"""Input validation shared by all blocks.

Shape and dtype problems raise `PiezojaxValueError` at trace time. Value problems (NaN, sign, ordering, uniform
time) go through one helper, `check_value`: a `PiezojaxValueError` when the value is concrete, `eqx.error_if` when it
is traced, so the same check also fires under `jit` and `vmap`.
"""

import contextlib
import contextvars
from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

_X = TypeVar("_X")


class PiezojaxError(Exception):
    """The base of every error piezojax and `fitting` raise themselves (`except pj.PiezojaxError` catches them all)."""


class PiezojaxValueError(PiezojaxError, ValueError):
    """Raised when an argument to a piezojax function has the wrong shape, type or value."""




def concrete_or_none(x: Array):
    """The numpy value of `x` if it is concrete (not traced), else None.

    Lets constructors raise a plain `ValueError` for bad concrete values, while traced values fall back to
    `eqx.error_if`.
    """
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


# how a failed check on a traced value acts: "raise" (`eqx.error_if`) or "nan" (see `refusals_as_nan`); read when the
# check is traced, so a compiled function keeps the mode it was traced under
_REFUSAL: contextvars.ContextVar[str] = contextvars.ContextVar("piezojax_refusal", default="raise")


@contextlib.contextmanager
def refusal_mode(mode: str) -> Iterator[None]:
    """Trace value checks in `mode`: `"raise"` (`eqx.error_if`, the default) or `"nan"` (see `refusals_as_nan`)."""
    if mode not in ("raise", "nan"):
        raise PiezojaxValueError(f"`mode` must be 'raise' or 'nan', got {mode!r}")
    token = _REFUSAL.set(mode)
    try:
        yield
    finally:
        _REFUSAL.reset(token)


@contextlib.contextmanager
def refusals_as_nan() -> Iterator[None]:
    """While tracing inside this context, a value check (`check_value`) that fails on traced values makes the checked
    floating values NaN instead of raising, separately for each member of a `vmap` batch.

    `eqx.error_if` cannot serve a batch whose members are independent problems: under `vmap` one failing member
    raises for all (and its `"nan"` mode makes every member NaN). A fleet of calibrations (`fitting.fit_fleet`)
    traces its steps in this context, so that a trial point one actuator's model refuses is a non-finite, rejected
    trial of that actuator alone, and `fitting`'s problems trace their residuals in it too (an `eqx.error_if`
    check is a host callback, which keeps a compiled program out of the persistent compilation cache). Concrete
    values still raise `PiezojaxValueError`. Only the tracing matters: a function compiled inside the context keeps
    NaN refusals when called outside it, so jit such a function only inside it.
    """
    with refusal_mode("nan"):
        yield


def refusing_as_nan() -> bool:
    """Whether value checks are being traced as NaN refusals (inside `refusals_as_nan`): a block whose own failure
    test is not a `check_value` (diffrax's, say) reads it to fail as NaN instead of raising."""
    return _REFUSAL.get() == "nan"


def nan_where(bad, x):
    """`x` with every floating leaf NaN where `bad` (broadcast), the others unchanged: a NaN refusal."""
    return jtu.tree_map(lambda a: jnp.where(bad, jnp.nan, a) if eqx.is_inexact_array(a) else a, x)


def is_traced(x: PyTree) -> bool:
    """True if any leaf of `x` is a tracer (under `jit`, `vmap`, `grad`, ...), i.e. its value is not known now."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x))


def check_value(x: _X, ok: Callable[[_X], ArrayLike] | ArrayLike, message: str | Sequence[str]) -> _X:
    """The one value check: raise if `x` is concrete and invalid, attach `eqx.error_if` if it is traced.

    **Arguments:**

    - `x`: the checked array (or a tuple of arrays); when traced, the returned copy carries the check: use it in
      place of `x`.
    - `ok`: a predicate `ok(x)` giving a boolean array, True where `x` is valid (every entry must be True); or that
      boolean array itself. A predicate is evaluated eagerly for a concrete `x` even inside `jit` (a closed-over
      parameter stays concrete, which keeps e.g. the concrete `smoothing == 0` fast paths).
    - `message`: what is wrong, naming the argument, e.g. "`weights` contains NaN or infinite values". Or one message
      per entry of a 1-D `ok`: then the first failing entry's message is reported, still with a single
      `eqx.branched_error_if` when traced (one check to compile for several conditions).

    **Returns:** `x`, or `x` with the check attached when `x` or `ok` is traced.

    **Raises:** `PiezojaxValueError` with the message when the check fails on concrete values; the value of `x` is
    appended when `x` is one short array (at most 8 numbers).
    """
    messages = None if isinstance(message, str) else list(message)

    def attach(good):
        if _REFUSAL.get() == "nan":
            return nan_where(~jnp.all(jnp.asarray(good)), x)
        if messages is None:
            return eqx.error_if(x, ~jnp.all(good), message)
        good = jnp.asarray(good)
        return eqx.branched_error_if(x, ~jnp.all(good), jnp.argmin(good), messages)

    if is_traced(x):
        return attach(ok(x) if callable(ok) else ok)
    with jax.ensure_compile_time_eval():
        good = ok(x) if callable(ok) else ok
        traced = is_traced(good)
        if not traced:
            good = np.asarray(good)
    if traced:  # `ok` reads a traced value (or an array computed under `jit`): the check goes with the computation
        # (outside `ensure_compile_time_eval`, where `eqx.error_if` on a concrete `x` would fire at trace time)
        return attach(good)
    if not np.all(good):
        text = message if messages is None else messages[int(np.argmin(good))]
        if eqx.is_array(x) and x.size <= 8:
            value = np.asarray(x)
            text = f"{text}, got {value.tolist() if value.ndim else value.item()}"
        raise PiezojaxValueError(text)
    return x


def check_component(x, cls: type | tuple[type, ...], name: str, called: str):
    """`x` if it is an instance of `cls` (a type or a tuple of types) or `None`, else a `PiezojaxValueError` naming
    the argument `name`, the types it may have and how the component calls it (`called`, e.g. "creep(v, dt)"): a
    component field's interface, checked where the component is built."""
    if x is not None and not isinstance(x, cls):
        kinds = " or ".join(f"pj.{c.__name__}" for c in (cls if isinstance(cls, tuple) else (cls,)))
        raise PiezojaxValueError(f"`{name}` must be a {kinds} (called as {called}) or None, got {type(x).__name__}")
    return x


def check_same_shape(a: Array, name_a: str, b: Array, name_b: str) -> None:
    """Raise one `PiezojaxValueError` naming both when two parameter arrays that go together (a play's weight and
    threshold, a lag's stiffness and time constant) differ in shape — also for leaves replaced after construction
    (`eqx.tree_at`), whose shapes are known while tracing."""
    if jnp.shape(a) != jnp.shape(b):
        raise PiezojaxValueError(
            f"`{name_a}` and `{name_b}` must have the same shape, got {tuple(jnp.shape(a))} and "
            f"{tuple(jnp.shape(b))} (was one of them replaced, e.g. with `eqx.tree_at`?)"
        )


def check_finite(x: Array, name: str) -> Array:
    """`check_value` that every entry of `x` is finite, naming `name` (the dtype must be real floating)."""
    check_real_dtype(x, name)
    return check_value(x, lambda a: jnp.all(jnp.isfinite(a)), f"`{name}` contains NaN or infinite values")


def check_real_dtype(x: ArrayLike, name: str) -> None:
    """Raise naming `name` if `x` is complex or boolean (both are mistakes for a parameter or a signal)."""
    dtype = getattr(x, "dtype", None)
    if dtype is None:
        return
    if jnp.issubdtype(dtype, jnp.complexfloating):
        raise PiezojaxValueError(f"`{name}` must be real, got the complex dtype {np.dtype(dtype).name}")
    if jnp.issubdtype(dtype, jnp.bool_):
        raise PiezojaxValueError(f"`{name}` must be numbers, got a boolean array")


def as_float_array(x: ArrayLike, name: str, dtype=None) -> Array:
    """Convert to a real floating JAX array, naming `name` if that is impossible (complex, boolean, not numeric).

    A concrete argument gives a concrete array even inside `jit` (so its value checks run at trace time).
    """
    with jax.ensure_compile_time_eval():
        try:
            arr = jnp.asarray(x)
        except (TypeError, ValueError) as e:
            raise PiezojaxValueError(f"`{name}` must be array-like of floats, got {type(x).__name__}") from e
        check_real_dtype(arr, name)
        if not jnp.issubdtype(arr.dtype, jnp.floating):
            arr = arr.astype(dtype if dtype is not None else jnp.zeros(()).dtype)
        elif dtype is not None:
            arr = arr.astype(dtype)
    return arr


def as_parameter_array(x: ArrayLike, name: str, dtype=None) -> Array:
    """`as_float_array`, strongly typed: a Python scalar becomes a weak-typed array, and a weak-typed leaf retraces
    `jit` when a fitter swaps in a strongly typed value."""
    arr = as_float_array(x, name, dtype)
    if getattr(arr, "weak_type", False):
        with jax.ensure_compile_time_eval():
            arr = arr.astype(arr.dtype)
    return arr


def check_signal(x: ArrayLike, name: str = "signal", dtype=None) -> Array:
    """Validate a sampled signal: real (not complex or boolean), 1-D, non-empty, finite (`check_finite`)."""
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 1:
        raise PiezojaxValueError(
            f"`{name}` must be a 1-D signal of shape (time,), got shape {tuple(arr.shape)}; "
            "use jax.vmap for a batch of signals"
        )
    if arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return check_finite(arr, name)


def check_vector(x: ArrayLike, name: str, dtype=None, allow_empty: bool = False, finite: bool = True) -> Array:
    """Validate a 1-D real parameter vector; with `finite` (default) also that every entry is finite."""
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 1:
        raise PiezojaxValueError(f"`{name}` must be 1-D, got shape {tuple(arr.shape)}")
    if not allow_empty and arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return check_finite(arr, name) if finite else arr


def check_scalar(x: ArrayLike, name: str, dtype=None, finite: bool = True) -> Array:
    """Validate a real scalar parameter; with `finite` (default) also that it is finite."""
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 0:
        raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {tuple(arr.shape)}")
    return check_finite(arr, name) if finite else arr


def check_step(dt: ArrayLike, name: str = "dt", dtype=None) -> Array:
    """Validate a sample step: a real scalar, finite and > 0 (`check_value`), naming `name`."""
    arr = as_float_array(dt, name, dtype)
    if arr.ndim != 0:
        raise PiezojaxValueError(
            f"`{name}` must be a scalar sample step, got shape {tuple(arr.shape)}; a signal is sampled uniformly"
        )
    return check_value(arr, lambda x: jnp.isfinite(x) & (x > 0), f"`{name}` must be a finite sample step > 0")


def check_positive(x: Array, name: str, allow_zero: bool = False) -> Array:
    """`check_value` that every entry of `x` is finite and > 0 (>= 0 with `allow_zero`), naming `name`."""
    if allow_zero:
        return check_value(x, lambda a: jnp.all(jnp.isfinite(a) & (a >= 0)), f"`{name}` must be finite and >= 0")
    return check_value(x, lambda a: jnp.all(jnp.isfinite(a) & (a > 0)), f"`{name}` must be finite and > 0")


def check_positive_param(x: ArrayLike, name: str, allow_zero: bool = False, dtype=None) -> Array:
    """Constructor check of a scalar parameter: a real scalar, finite and > 0 (>= 0 with `allow_zero`), of `dtype`
    (default its own; a constructor gives the `param_dtype` of its arguments, so Python numbers follow them)."""
    x = as_parameter_array(x, name, dtype)
    if x.ndim != 0:
        raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {tuple(x.shape)}")
    return check_positive(x, name, allow_zero)


def check_scalar_param(x: ArrayLike, name: str, dtype=None, finite: bool = True) -> Array:
    """Constructor check of a signed scalar parameter: a real scalar, finite (with `finite`; else only not NaN, e.g. a
    limit that may be infinite), of `dtype` (as `check_positive_param`)."""
    x = as_parameter_array(x, name, dtype)
    if x.ndim != 0:
        raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {tuple(x.shape)}")
    if finite:
        return check_finite(x, name)
    return check_value(x, lambda a: ~jnp.isnan(a), f"`{name}` must not be NaN")


def check_nonzero(x: Array, name: str) -> Array:
    """`check_value` that `x` is finite and nonzero, naming `name`."""
    return check_value(x, lambda a: jnp.all(jnp.isfinite(a) & (a != 0)), f"`{name}` must be finite and nonzero")


def checked(module):
    """`module.check()` where its class defines `check` (every piezojax block: parameter checks attached, see
    `check_value`); a module of the user's own without one as it is. For components held by interface
    (`AbstractCell`: a loop's observer, a feedforward's inverse), whose type says nothing about checks."""
    check = getattr(type(module), "check", None)
    return module.check() if callable(check) else module


def error_if_not_positive(module: eqx.Module, names: tuple[str, ...], allow_zero: tuple[str, ...] = ()) -> eqx.Module:
    """`check_positive` on the named scalar fields (> 0, or >= 0 for those in `allow_zero`); the checked module."""
    checked = tuple(check_positive(getattr(module, n), n, n in allow_zero) for n in names)
    return eqx.tree_at(lambda m: tuple(getattr(m, n) for n in names), module, checked)


def error_if_not_finite(module: eqx.Module, names: tuple[str, ...]) -> eqx.Module:
    """`check_finite` on the named fields; the checked module."""
    checked = tuple(check_finite(getattr(module, n), n) for n in names)
    return eqx.tree_at(lambda m: tuple(getattr(m, n) for n in names), module, checked)
