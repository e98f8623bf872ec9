"""Reparametrisations that map unconstrained arrays to valid parameters, for fitting.

A model's constrained field is replaced (with `eqx.tree_at`, which bypasses `__init__` validation) by a wrapper holding
an unconstrained array `raw`; `unwrap(tree)` turns every wrapper back into its constrained value. A least-squares solver
then moves `raw` freely and every point it visits is a valid model:

```python
pi = pj.PrandtlIshlinskii(weights, thresholds, w0=1.0)
params = pj.constrain(pi, lambda m: m.weights, pj.Positive)
params = pj.constrain(params, lambda m: m.thresholds, pj.OrderedPositive)
model = pj.unwrap(params)  # a valid PrandtlIshlinskii for any value of the raw arrays
```
"""

import abc
import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

from ._checks import PiezojaxValueError, as_float_array, check_finite, check_value

_T = TypeVar("_T")


def softplus(x: ArrayLike) -> Array:
    r"""Numerically safe $\log(1 + e^x)$ (gradient $\sigma(x)$ everywhere, no overflow)."""
    return jax.nn.softplus(x)


def inv_softplus(y: ArrayLike) -> Array:
    r"""Inverse of `softplus` for $y > 0$: $x = y + \log(-\mathrm{expm1}(-y))$ (accurate for small and large y)."""
    y = jnp.asarray(y)
    return y + jnp.log(-jnp.expm1(-y))


class AbstractReparam(eqx.Module):
    """A constrained parameter stored as an unconstrained array `raw`; `unwrap()` gives the constrained value."""

    raw: eqx.AbstractVar[Array]

    @abc.abstractmethod
    def unwrap(self) -> Array:
        """The constrained value."""


class Positive(AbstractReparam):
    r"""Elementwise positive parameter: $x = \mathrm{softplus}(\mathrm{raw}) > 0$.

    **Arguments:**

    - `raw`: unconstrained array (any shape).

    Use `Positive.from_value(x)` to wrap an existing positive value.
    """

    raw: Array

    def __init__(self, raw: ArrayLike):
        self.raw = check_finite(as_float_array(raw, "raw"), "raw")

    @classmethod
    def from_value(cls, value: ArrayLike) -> "Positive":
        """Wrap a finite, strictly positive `value` (raises naming `value` otherwise)."""
        value = check_finite(as_float_array(value, "value"), "value")
        value = check_value(value, lambda x: jnp.all(x > 0), "`value` must be strictly positive for Positive")
        return cls(inv_softplus(value))

    def unwrap(self) -> Array:
        return softplus(self.raw)


class OrderedPositive(AbstractReparam):
    r"""Strictly ascending, strictly positive 1-D parameter (e.g. play-operator thresholds).

    $x_i = \mathrm{lower} + \sum_{j \le i} \mathrm{softplus}(\mathrm{raw}_j)$, so
    $\mathrm{lower} < x_1 < x_2 < \dots$ for every value of `raw`. With the default `lower = 0` the first threshold
    stays off $r = 0$, which is reserved for the explicit linear term of a Prandtl–Ishlinskii operator.

    **Arguments:**

    - `raw`: unconstrained 1-D array.
    - `lower`: the bound every entry stays strictly above (a constant, not fitted).
    """

    raw: Array
    lower: float = eqx.field(static=True)

    def __init__(self, raw: ArrayLike, lower: float = 0.0):
        if not np.isfinite(lower):
            raise PiezojaxValueError(f"`lower` must be a finite number, got {lower}")
        self.raw = check_finite(as_float_array(raw, "raw"), "raw")
        self.lower = lower

    @classmethod
    def from_value(cls, value: ArrayLike, lower: float = 0.0) -> "OrderedPositive":
        """Wrap a finite, strictly ascending 1-D `value` with every entry > `lower`."""
        value = check_finite(as_float_array(value, "value"), "value")
        if value.ndim != 1:
            raise PiezojaxValueError(f"`value` must be 1-D for OrderedPositive, got shape {value.shape}")
        value = check_value(  # checked on `value`, so that the message shows it (not its gaps)
            value, lambda x: jnp.all(jnp.diff(x, prepend=jnp.asarray([lower], x.dtype)) > 0),
            f"`value` must be strictly ascending and above {lower} for OrderedPositive",
        )
        return cls(inv_softplus(jnp.diff(value, prepend=jnp.asarray([lower], value.dtype))), lower)

    def unwrap(self) -> Array:
        return self.lower + jnp.cumsum(softplus(self.raw))


class Bounded(AbstractReparam):
    r"""Parameter inside an open interval: $x = \mathrm{low} + (\mathrm{high} - \mathrm{low})\,\sigma(\mathrm{raw})$.

    **Arguments:**

    - `raw`: unconstrained array.
    - `low`, `high`: the bounds (constants, `low < high`).
    """

    raw: Array
    low: float = eqx.field(static=True)
    high: float = eqx.field(static=True)

    def __init__(self, raw: ArrayLike, low: float, high: float):
        if not (np.isfinite(low) and np.isfinite(high) and low < high):
            raise PiezojaxValueError(f"Bounded needs finite `low` < `high`, got low={low}, high={high}")
        self.raw = check_finite(as_float_array(raw, "raw"), "raw")
        self.low, self.high = low, high

    @classmethod
    def from_value(cls, value: ArrayLike, low: float, high: float) -> "Bounded":
        """Wrap a `value` strictly inside `(low, high)`."""
        value = as_float_array(value, "value")
        value = check_value(
            value, lambda x: jnp.all((x > low) & (x < high)), f"`value` must lie strictly inside ({low}, {high})"
        )
        p = (value - low) / (high - low)
        return cls(jnp.log(p) - jnp.log1p(-p), low, high)

    def unwrap(self) -> Array:
        return self.low + (self.high - self.low) * jax.nn.sigmoid(self.raw)


class Fractions(AbstractReparam):
    r"""Positive fractions with a sum below one (e.g. `LagCreep.fractions`): $x_i = e^{r_i}/(1 + \sum_j e^{r_j})$.

    Every `raw` gives $x_i > 0$ and $\sum_i x_i < 1$ (the remainder $1 - \sum x_i$ is the implicit last share).

    **Arguments:**

    - `raw`: unconstrained 1-D array.
    """

    raw: Array

    def __init__(self, raw: ArrayLike):
        self.raw = check_finite(as_float_array(raw, "raw"), "raw")
        if self.raw.ndim != 1:
            raise PiezojaxValueError(f"`raw` must be 1-D for Fractions, got shape {self.raw.shape}")

    @classmethod
    def from_value(cls, value: ArrayLike) -> "Fractions":
        """Wrap a 1-D `value` with every entry > 0 and a sum < 1."""
        value = check_finite(as_float_array(value, "value"), "value")
        if value.ndim != 1:
            raise PiezojaxValueError(f"`value` must be 1-D for Fractions, got shape {value.shape}")
        value = check_value(
            value, lambda x: jnp.all(x > 0) & (jnp.sum(x) < 1), "`value` must be > 0 with a sum < 1 for Fractions"
        )
        return cls(jnp.log(value) - jnp.log1p(-jnp.sum(value)))

    def unwrap(self) -> Array:
        # softmax over [raw, 0] without the last entry, computed stably
        z = jnp.concatenate([self.raw, jnp.zeros((1,), self.raw.dtype)])
        return jax.nn.softmax(z)[:-1]


_SETTING = "piezojax.setting"


def setting(**kwargs) -> Any:
    """A dataclass field (`eqx.field`, same keyword arguments) for a *setting* of a block rather than a parameter: an
    array the block computes with that a calibration does not fit by default, such as a hysteresis operator's
    `smoothing` (a continuation setting: 0 is the exact operator). `fitting.free_mask` (and so `fitting.fit` without
    `free`) leaves settings out; naming one in `free` still frees it.

    ```python
    class MyOperator(pj.AbstractHysteresis):
        thresholds: Array
        smoothing: Array = pj.setting()
    ```
    """
    metadata = dict(kwargs.pop("metadata", None) or {})
    metadata[_SETTING] = True
    return eqx.field(metadata=metadata, **kwargs)


def setting_key_paths(tree: PyTree[Any]) -> list[tuple]:
    """The key paths (as `jax.tree_util.tree_flatten_with_path` spells them) of every field declared with
    `pj.setting()` in the modules of `tree`, whatever the field holds (an array, a reparametrisation wrapper)."""
    out: list[tuple] = []

    def walk(x, prefix):
        if isinstance(x, eqx.Module):
            for f in dataclasses.fields(x):
                path = (*prefix, jtu.GetAttrKey(f.name))
                if f.metadata.get(_SETTING, False):
                    out.append(path)
                else:
                    walk(getattr(x, f.name, None), path)
        elif isinstance(x, list | tuple):
            for i, v in enumerate(x):
                walk(v, (*prefix, jtu.SequenceKey(i)))
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, (*prefix, jtu.DictKey(k)))

    walk(tree, ())
    return out


def _is_reparam(x: Any) -> bool:
    return isinstance(x, AbstractReparam)


def unwrap(tree: PyTree[Any]) -> PyTree[Any]:
    """Replace every `AbstractReparam` in `tree` by its constrained value (works under jit/vmap/grad)."""
    return jtu.tree_map(lambda x: x.unwrap() if _is_reparam(x) else x, tree, is_leaf=_is_reparam)


def constrain(
    model: _T,
    where: Callable[[_T], Any],
    reparam: type[AbstractReparam] | Callable[[Array], AbstractReparam],
) -> _T:
    """Return `model` with the array selected by `where` wrapped by `reparam.from_value`.

    **Arguments:**

    - `model`: an equinox Module (or any PyTree).
    - `where`: selects the array to constrain, as in `eqx.tree_at`, e.g. `lambda m: m.weights`.
    - `reparam`: an `AbstractReparam` subclass with `from_value(value)` (`Positive`, `OrderedPositive`), or any
      callable mapping the current value to a wrapper (e.g. `lambda x: Bounded.from_value(x, 0.0, 1.0)`).

    **Returns:** the model with the wrapper in place; `unwrap` it before use.
    """
    factory = reparam.from_value if isinstance(reparam, type) else reparam
    return eqx.tree_at(where, model, replace_fn=factory)
