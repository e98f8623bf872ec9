"""The typed options of a block kind: `KindOptions`, and the options every kind of a table shares
(`HysteresisOptions`: the output polynomial; `CreepOptions`: the structure).

A kind declares its options as a frozen dataclass subclassing its table's options (`TABLE_OPTIONS`), and its `parse`
returns an instance; its methods read attributes (`o.order`). The kind's own CONFIG keys are the fields it adds
(`BlockKind.keys`); the table's common keys are read by the generic configuration code and filled in with
`dataclasses.replace`.
"""

import dataclasses
import warnings

import numpy as np


def _deprecated(key, how: str, names) -> None:
    if key in names:
        hint = f"read the attribute `.{key}` instead"
    else:
        hint = f"read the attributes ({', '.join(names) or 'none'})"
    warnings.warn(f"dict-style access to a kind's options ({how}) is deprecated: the options are a dataclass; {hint}",
                  DeprecationWarning, stacklevel=3)


@dataclasses.dataclass(frozen=True)
class KindOptions:
    """The validated options of a block kind: a frozen dataclass, one field per CONFIG key (a parameter the file does
    not give is `None`). Subclass it (through the table's `HysteresisOptions` / `CreepOptions`, or directly for
    `[dynamics]`) with `@dataclasses.dataclass(frozen=True)`.

    For code written when the options were a dict, `options[key]` (the attribute; `KeyError` if none),
    `options.get(key, default)` (`default` where the attribute is `None` or absent) and `key in options` (the attribute
    exists and is not `None`) still work and warn (`DeprecationWarning`) naming the attribute to read instead.
    """

    def _names(self) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(self))

    def __getitem__(self, key: str):
        names = self._names()
        _deprecated(key, f"[{key!r}]", names)
        if key not in names:
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default=None):
        """Deprecated: the attribute `key`, or `default` where it is `None` (not given) or not an option."""
        names = self._names()
        _deprecated(key, f".get({key!r})", names)
        value = getattr(self, key) if key in names else None
        return default if value is None else value

    def __contains__(self, key) -> bool:
        names = self._names()
        _deprecated(key, f"{key!r} in", names)
        return key in names and getattr(self, key) is not None


@dataclasses.dataclass(frozen=True, kw_only=True)
class HysteresisOptions(KindOptions):
    """The keys every `[hysteresis]` kind except `"none"` accepts: the output polynomial around the operator
    (`pj.OutputPolynomial`): its degree `polynomial` (0: none, else 2 and above), its `coefficients` (degree - 1
    values; `None`: not given) and `polynomial_scale` (`None`: from the data)."""

    polynomial: int = 0
    coefficients: np.ndarray | None = None
    polynomial_scale: float | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class CreepOptions(KindOptions):
    """The key every `[creep]` kind except `"none"` accepts: `structure`, `"series"` or `"parallel"` as the file
    gives it (`None`: the kind's default, `ModelConfig.creep_structure`)."""

    structure: str | None = None


TABLE_OPTIONS: dict[str, type[KindOptions]] = {
    "hysteresis": HysteresisOptions, "creep": CreepOptions, "dynamics": KindOptions,
}


def common_keys(table: str) -> tuple[str, ...]:
    """The keys of `table` that the table's options class declares (read for every kind except `"none"`)."""
    base = TABLE_OPTIONS.get(table, KindOptions)
    return tuple(f.name for f in dataclasses.fields(base))
