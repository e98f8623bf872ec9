"""Input validation shared by all blocks.

Shape problems raise `ValueError` at trace time; value problems that depend on data (NaN, ordering, uniform time)
are checked with `eqx.error_if` so they also fire under `jit` and `vmap`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


class PiezojaxValueError(ValueError):
    """Raised when an argument to a piezojax function has the wrong shape, type or value."""


def common_float_dtype(*xs: ArrayLike) -> np.dtype:
    """The floating dtype that holds every argument without loss (float32 stays float32).

    Explicit, so it works under `jax_numpy_dtype_promotion='strict'`.
    """
    dtype = None
    for x in xs:
        d = np.dtype(x.dtype) if hasattr(x, "dtype") else np.asarray(x).dtype
        if not jnp.issubdtype(d, jnp.inexact):
            continue
        dtype = d if dtype is None else np.promote_types(dtype, d)
    if dtype is None:
        dtype = jnp.zeros(()).dtype  # default float dtype (float32 or float64 under x64)
    return jax.dtypes.canonicalize_dtype(dtype)


def as_float_array(x: ArrayLike, name: str, dtype=None) -> Array:
    """Convert to a floating JAX array, naming `name` if that is impossible."""
    try:
        arr = jnp.asarray(x)
    except (TypeError, ValueError) as e:
        raise PiezojaxValueError(f"`{name}` must be array-like of floats, got {type(x).__name__}") from e
    if not jnp.issubdtype(arr.dtype, jnp.inexact):
        arr = arr.astype(dtype if dtype is not None else jnp.zeros(()).dtype)
    elif dtype is not None:
        arr = arr.astype(dtype)
    return arr


def check_signal(x: ArrayLike, name: str = "signal", dtype=None) -> Array:
    """Validate a sampled signal: 1-D, non-empty, finite (NaN/inf checked with `eqx.error_if`)."""
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 1:
        raise PiezojaxValueError(
            f"`{name}` must be a 1-D signal of shape (time,), got shape {tuple(arr.shape)}; "
            "use jax.vmap for a batch of signals"
        )
    if arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return check_finite(arr, name)


def check_finite(x: Array, name: str) -> Array:
    """`eqx.error_if` on any NaN or infinite entry, naming `name`."""
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"`{name}` contains NaN or infinite values")


def check_vector(x: ArrayLike, name: str, dtype=None, allow_empty: bool = False) -> Array:
    """Validate a 1-D parameter vector (shape only; values are checked by the caller)."""
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 1:
        raise PiezojaxValueError(f"`{name}` must be 1-D, got shape {tuple(arr.shape)}")
    if not allow_empty and arr.shape[0] == 0:
        raise PiezojaxValueError(f"`{name}` must not be empty")
    return arr


def check_scalar(x: ArrayLike, name: str, dtype=None) -> Array:
    arr = as_float_array(x, name, dtype)
    if arr.ndim != 0:
        raise PiezojaxValueError(f"`{name}` must be a scalar, got shape {tuple(arr.shape)}")
    return arr


def concrete_or_none(x: Array):
    """The numpy value of `x` if it is concrete (not traced), else None.

    Lets constructors raise a plain `ValueError` for bad concrete values, while traced values fall back to
    `eqx.error_if`.
    """
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None
