"""Floating dtypes: which dtype a computation runs in, and casting a module's parameters to it.

Every block runs in the common floating dtype of its parameters and signals (float32 stays float32, float64 under
x64 stays float64); these are the helpers that decide it, used by every family.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import ArrayLike

from ._checks import PiezojaxValueError
from ._parametrisation import AbstractReparam


def common_float_dtype(*xs: ArrayLike) -> np.dtype:
    """The floating dtype that holds every argument without loss (float32 stays float32).

    Values without a dtype (Python numbers, lists, tuples) follow the arrays, as in `param_dtype` (like JAX's weakly
    typed scalars; unlike JAX, for lists too): a float32 signal with `dt=1e-4` stays float32; only when no argument
    has a floating dtype do they decide (the default float dtype). Explicit, so it works under
    `jax_numpy_dtype_promotion='strict'`. Complex arguments are ignored here (they are rejected, naming the argument,
    by `as_float_array`).
    """
    dtype = None
    for x in xs:
        if not hasattr(x, "dtype"):
            continue
        d = np.dtype(x.dtype)
        if not jnp.issubdtype(d, jnp.floating):
            continue
        dtype = d if dtype is None else np.promote_types(dtype, d)
    if dtype is None:
        dtype = jnp.zeros(()).dtype  # default float dtype (float32 or float64 under x64)
    return jax.dtypes.canonicalize_dtype(dtype)


def param_dtype(*xs):
    """The floating dtype of the array-valued arguments (Python scalars and lists follow them; complex arguments are
    left to `as_float_array`, which rejects them naming the argument)."""
    dtypes = [np.dtype(x.dtype) for x in xs if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)]
    if not dtypes:
        return jnp.zeros(()).dtype
    return jax.dtypes.canonicalize_dtype(np.result_type(*dtypes))


def cast_module(module: eqx.Module, dtype) -> eqx.Module:
    """Cast every floating array leaf of `module` to `dtype` (so float32 signals run in float32)."""

    def cast(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and x.dtype != dtype:
            return x.astype(dtype)
        return x

    return jtu.tree_map(cast, module)


def module_float_dtype(module: eqx.Module, *extra: ArrayLike):
    """The common floating dtype of a module's array leaves and `extra` arrays. A module holding reparametrised
    leaves (`pj.constrain`'s wrappers) cannot compute: `PiezojaxValueError` saying to `pj.unwrap` it."""
    wrapped = [x for x in jtu.tree_leaves(module, is_leaf=lambda x: isinstance(x, AbstractReparam))
               if isinstance(x, AbstractReparam)]
    if wrapped:
        raise PiezojaxValueError(
            f"{type(module).__name__} holds reparametrised parameters ({type(wrapped[0]).__name__}, from "
            "`pj.constrain`): compute with `pj.unwrap(model)` (a fit's `result.model` is unwrapped already)"
        )
    leaves = [x for x in jtu.tree_leaves(module) if eqx.is_array(x)]
    return common_float_dtype(*leaves, *extra)


def matmul(a: ArrayLike, b: ArrayLike) -> jax.Array:
    """`jnp.matmul(a, b)` at the full precision of its dtype on every backend (for 1-D and 2-D operands the same as
    `jnp.dot`; unlike it, no scalars, and operands above 2-D broadcast as stacks of matrices).

    JAX's default precision lets GPUs multiply float32 matrices in TF32 (a 10-bit mantissa): on an H200 the PI
    operator's float32 Jacobian, whose columns are products of the plays' states and weights, came out up to 3e-4
    relative from the same Jacobian by autodiff through the scan. The matrix products of piezojax's models and of
    `fitting`'s normal equations go through here (polynomial products through `polymul`). On the CPU, and in float64
    everywhere, it is the plain product.
    """
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def polymul(a: ArrayLike, b: ArrayLike) -> jax.Array:
    """`jnp.polymul(a, b)` of two 1-D coefficient arrays (highest power first) at the full precision of their dtype:
    JAX forms it as a convolution, which GPUs also run in TF32 for float32 by default (see `matmul`)."""
    return jnp.convolve(a, b, precision=jax.lax.Precision.HIGHEST)
