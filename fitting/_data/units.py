"""Units of the data columns: SI prefixes (`unit_scale`, `parse_units`) and the plausibility checks that catch a
column in the wrong unit."""

from collections.abc import Mapping

import numpy as np

from piezojax import PiezojaxValueError

from .experiment import COLUMNS, UNITS, Experiment

_QUANTITIES = {"s": "time", "V": "voltage", "m": "length", "N": "force", "C": "charge", "A": "current"}
_PREFIXES = {"k": 1e3, "": 1.0, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "μ": 1e-6, "n": 1e-9, "p": 1e-12}


class UnitWarning(UserWarning):
    """A column's magnitude is implausible for its SI unit (e.g. a displacement spanning metres: probably µm)."""


def unit_scale(column: str, unit: str, where: str = "units") -> float:
    """The factor that converts `column` from `unit` to its SI unit (`UNITS`): `unit_scale("displacement", "um")`
    is 1e-6. Units are the SI unit with an optional prefix k, m, u (or µ), n, p.

    Raises `PiezojaxValueError` naming `where`, the column and the units it takes."""
    if column not in COLUMNS:
        raise PiezojaxValueError(f"{where}: unknown column {column!r}; columns are {list(COLUMNS)}")
    base = UNITS[column]
    if isinstance(unit, str):
        u = unit.strip()
        if u.endswith(base) and u[: len(u) - len(base)] in _PREFIXES:
            return _PREFIXES[u[: len(u) - len(base)]]
    allowed = ", ".join(p + base for p in ("k", "", "m", "u", "n", "p"))
    raise PiezojaxValueError(
        f"{where}: unknown unit {unit!r} for column {column!r}, a {_QUANTITIES[base]}; allowed: {allowed} "
        f"(u or µ for micro)"
    )


def parse_units(units, where: str = "`units`") -> dict[str, float]:
    """Validate a `{column: unit}` mapping (e.g. `{"displacement": "um", "t": "ms"}`); return `{column: scale to
    SI}`. `None` means every column is in SI units."""
    if units is None:
        return {}
    if not isinstance(units, Mapping):
        raise PiezojaxValueError(f"{where} must be a mapping {{column: unit}}, got {type(units).__name__}")
    return {str(k): unit_scale(str(k), v, where) for k, v in units.items()}


# Plausible magnitudes for a piezoelectric actuator in SI units: (column, statistic, upper bound, hint, the unit
# to suggest).
_PLAUSIBLE = (
    ("v_in", "peak", 1e4, "V (kilovolts are the upper end of piezo drives; is it in mV?)", "mV"),
    ("v_out", "peak", 1e4, "V (is it in mV?)", "mV"),
    ("displacement", "range", 1e-2, "m (piezo strokes are below a few millimetres; is it in µm, nm or mm?)", "um"),
    ("force", "peak", 1e5, "N (is it in mN?)", "mN"),
    ("charge", "peak", 1.0, "C (is it in µC or nC?)", "uC"),
    ("current", "peak", 1e2, "A (is it in mA or µA?)", "mA"),
)


def plausibility_warnings(exp: "Experiment", units: Mapping[str, str] | None = None) -> list[str]:
    """Messages for columns of `exp` whose magnitude is implausible in SI units (a record in µm read as metres,
    in mV read as volts, ...); empty if everything looks plausible. `units`: the units declared on loading (a
    column with a declared unit is reported as such, not asked to declare one)."""
    units = dict(units or {})
    out = []
    for col, stat, bound, hint, suggest in _PLAUSIBLE:
        if col not in exp.columns():
            continue
        a = exp[col]
        value = float(np.ptp(a)) if stat == "range" else float(np.max(np.abs(a)))
        if value <= bound:
            continue
        if col in units:
            out.append(f"{exp._label()}: column {col!r}, declared in {units[col]!r}, has a {stat} of {value:.4g} "
                       f"{UNITS[col]} after conversion, implausible for a piezo record — check its declared unit")
        else:
            out.append(
                f"{exp._label()}: column {col!r} has a {stat} of {value:.4g} {hint} — declare the column's unit "
                f"(e.g. units = {{{col} = \"{suggest}\"}} in [data], or --units {col}={suggest})"
            )
    if exp.dt < 1e-8 or exp.dt > 10.0:
        if "t" in units:
            out.append(f"{exp._label()}: sampling step dt = {exp.dt:.4g} s (t declared in {units['t']!r}) is "
                       "implausible for a piezo record — check its declared unit")
        else:
            out.append(
                f"{exp._label()}: sampling step dt = {exp.dt:.4g} s is implausible for a piezo record (is 't' in ms "
                "or µs? declare its unit, e.g. --units t=ms)"
            )
    return out

