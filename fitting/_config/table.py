"""One TOML table of a CONFIG (`ConfigTable`: typed, named reads of its keys), the sizes a CONFIG may ask
for, and the small helpers every kind shares."""

import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

# NNLS over plays x samples) or the fit's memory grows past what the method is meant for.
MAX_PLAYS = 100
MAX_ELEMENTS = 100
MAX_LEVELS_PREISACH = 30
MAX_CREEP_ORDER = 10
MAX_SUBSTEPS = 64
MAX_POLYNOMIAL = 6
DYNAMICS_ORDERS = (0, 1, 2, 3, 4, 5, 6, 7, 8)

TINY = np.finfo(float).tiny
# plays whose thresholds lie closer than this fraction of the largest |input| count as one when re-seeding
DUPLICATE_THRESHOLD = 1e-4
# plays of the PI surrogate that starts creep and dynamics jointly when the hysteresis is of another family
SURROGATE_PLAYS = 10


def finite_number(x) -> bool:
    """A TOML number (not a bool) that is finite as a float (an integer of 400 digits is not)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def chord(v: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against v through the origin (1 when v is zero)."""
    den = float(np.dot(v, v))
    return float(np.dot(v, y)) / den if den > 0 else 1.0


class Negative(pj.AbstractReparam):
    r"""Elementwise negative parameter (real poles of the dynamics): $x = -\mathrm{softplus}(\mathrm{raw}) < 0$."""

    raw: jax.Array = eqx.field(converter=jnp.asarray)

    @classmethod
    def from_value(cls, value) -> "Negative":
        value = jnp.asarray(value)
        return cls(pj.inv_softplus(-value))

    def unwrap(self) -> jax.Array:
        return -pj.softplus(self.raw)


# ------------------------------------------------------------------------------------------------ one TOML table


class ConfigTable:
    """One TOML table of a CONFIG, with the file and table names for its error messages.

    **Arguments:**

    - `source`: the file name (the start of every error message).
    - `name`: the table's name (`hysteresis`, ...).
    - `data`: the table's contents.
    - `allowed`: the keys allowed besides `kind`; any other key is an error listing them.
    - `kind`: the kind named in the table, for the error message.

    The readers (`number`, `integer`, `string`, `vector`, `sized_vectors`) return `default` (`None`) when the key is
    absent and raise one `PiezojaxValueError` naming the file, table and key otherwise.
    """

    def __init__(self, source: str, name: str, data: Any, allowed: tuple[str, ...], kind: str | None = None):
        self.source, self.name = source, name
        if not isinstance(data, Mapping):
            raise self.error(f"must be a table ([{name}]), got {type(data).__name__}")
        self.data = dict(data)
        unknown = [k for k in self.data if k not in allowed and k != "kind"]
        if unknown:
            what = f" for kind {kind!r}" if kind is not None else ""
            raise self.error(
                f"unknown key {unknown[0]!r}; allowed keys{what}: {', '.join(allowed) if allowed else '(none)'}"
            )

    def error(self, msg: str, key: str | None = None) -> PiezojaxValueError:
        """A `PiezojaxValueError` `"<file>: [<table>] <key>: <msg>"` (to raise)."""
        where = f"[{self.name}] {key}" if key else f"[{self.name}]"
        return PiezojaxValueError(f"{self.source}: {where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def number(self, key: str, default=None, *, positive=False, nonnegative=False, nonzero=False):
        if key not in self.data:
            return default
        x = self.data[key]
        if not finite_number(x):
            raise self.error(f"must be a finite number, got {x!r}", key)
        if positive and not x > 0:
            raise self.error(f"must be > 0, got {x!r}", key)
        if nonnegative and not x >= 0:
            raise self.error(f"must be >= 0, got {x!r}", key)
        if nonzero and x == 0:
            raise self.error("must be nonzero", key)
        return float(x)

    def integer(self, key: str, default=None, *, minimum=None, maximum=None, allowed=None):
        if key not in self.data:
            return default
        x = self.data[key]
        if isinstance(x, bool) or not isinstance(x, int):
            raise self.error(f"must be an integer, got {x!r}", key)
        if allowed is not None and x not in allowed:
            raise self.error(f"must be one of {', '.join(map(str, allowed))}; got {x}", key)
        if minimum is not None and x < minimum:
            raise self.error(f"must be >= {minimum}, got {x}", key)
        if maximum is not None and x > maximum:
            raise self.error(f"must be <= {maximum} (the documented upper bound), got {x}", key)
        return x

    def string(self, key: str, allowed: tuple[str, ...], default=None):
        if key not in self.data:
            return default
        x = self.data[key]
        if not isinstance(x, str) or x not in allowed:
            raise self.error(f"unknown value {x!r}; allowed values: {', '.join(allowed)}", key)
        return x

    def vector(self, key: str, length: int | None, *, positive=False, nonnegative=False, negative=False,
               ascending=False):
        if key not in self.data:
            return None
        x = self.data[key]
        if not isinstance(x, list) or not all(finite_number(v) for v in x):
            raise self.error(f"must be a list of finite numbers, got {x!r}", key)
        if length is not None and len(x) != length:
            raise self.error(f"must have {length} entries (from the block's size), got {len(x)}", key)
        if not x:
            raise self.error("must not be empty", key)
        a = np.asarray(x, dtype=np.float64)
        if positive and not np.all(a > 0):
            raise self.error(f"entries must be > 0, got {x}", key)
        if nonnegative and not np.all(a >= 0):
            raise self.error(f"entries must be >= 0, got {x}", key)
        if negative and not np.all(a < 0):
            raise self.error(f"entries must be < 0, got {x}", key)
        if ascending and not np.all(np.diff(a) > 0):
            raise self.error(f"entries must be strictly ascending, got {x}", key)
        return a

    def sized_vectors(
        self, size_key: str, default_size: int, maximum: int, specs: dict[str, dict], *, minimum: int = 1
    ) -> tuple[int, list]:
        """A block of `size_key` elements (`minimum` to `maximum`) and its per-element vectors `specs` (name →
        `vector` options): the size is given, or taken from the vectors given (which must agree), else
        `default_size`."""
        n = self.integer(size_key, None, minimum=minimum, maximum=maximum)
        vectors = [self.vector(name, n, **opts) if n != 0 else self._absent(name, size_key)
                   for name, opts in specs.items()]
        sizes = {len(x) for x in vectors if x is not None}
        if n is None:
            if len(sizes) > 1:
                names = list(specs)
                raise self.error(f"`{names[0]}` and `{names[1]}` must have the same length", names[0])
            n = sizes.pop() if sizes else default_size
            if n > maximum:
                name = next(k for k, x in zip(specs, vectors) if x is not None)
                raise self.error(f"has {n} entries; at most {maximum} (the documented upper bound of "
                                 f"`{size_key}`)", name)
        return n, vectors

    def _absent(self, name: str, size_key: str):
        if name in self.data:
            raise self.error(f"not used with {size_key} = 0", name)
        return None



class StartWarning(UserWarning):
    """One of the data-driven starts failed and another was used."""



def f64(x) -> jax.Array:
    """A float64 JAX array of `x` (CONFIG values are float64 whatever the default dtype)."""
    return jnp.asarray(np.asarray(x, np.float64))
